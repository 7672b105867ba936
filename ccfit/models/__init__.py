"""World models: one interface (base.py), TD-MPC2, PWM."""

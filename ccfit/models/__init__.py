"""World models: one interface (base.py), TD-MPC2, PWM."""

from ccfit.models import dreamerv3  # noqa: F401, E402 - registers "dreamerv3"

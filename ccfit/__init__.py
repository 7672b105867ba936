"""ccfit: world models trained continually on the ccdata suites, scored by BWT and FWT."""

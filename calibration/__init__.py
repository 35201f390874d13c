"""Calibration of thermocomp models: fit from eddy-current runs, validate in free run."""

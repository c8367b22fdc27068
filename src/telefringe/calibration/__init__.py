"""Calibration of devices and rigs: bundle adjustment, closed-form starts, uncertainty."""

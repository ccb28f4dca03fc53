"""Sensor calibration *fitting*: magnetometer ellipsoid, gyro bias at rest, six-position
accelerometer, and magnetic declination from the World Magnetic Model.

Applying a calibration to samples happens in one place only:
:mod:`ahrs_service.core.calibration`.
"""

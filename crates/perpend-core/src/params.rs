//! Stored-parameter format of the sensor head's calibration and configuration.

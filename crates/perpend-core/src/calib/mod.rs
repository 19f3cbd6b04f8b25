//! Calibration of the sensor head (Chen §3.2 EKF, batch least squares).

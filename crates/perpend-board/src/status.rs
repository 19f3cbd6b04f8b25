//! The measurement status word (object 0x2005): bit constants.
//!
//! The contract is defined in `perpend_can::status` (re-exported here); the
//! board's meaning of each bit:
//!
//! ```text
//! bit 4i+0  sensor i valid             (i = 0..3; sensors 1..4 on the bus)
//! bit 4i+1  sensor i out of range / saturated (NE43 3.6..3.8 or 20.5..21 mA)
//! bit 4i+2  sensor i open loop         (< 3.6 mA)
//! bit 4i+3  sensor i overcurrent       (> 21 mA)
//! bit 16    degraded: plane from three sensors
//! bit 17    uncalibrated (factory head: no stored record, or stamp 0)
//! bit 18    plane RMS residual above the limit (four sensors)
//! bit 19    no valid plane: the normal/angle values are not a measurement
//! bit 20    a sensor is stuck (its reading did not change for
//!           `stuck_samples` samples)
//! bit 21    configuration invalid
//! ```
//!
//! A sensor whose nibble is all zero while bit 20 is clear was dropped by
//! the jump detector (spatter, hole edge: see [`crate::acq::Channel`]); with
//! bit 20 set, the sensors with an all-zero nibble are the stuck ones.

// One definition of the contract: the constants are `perpend-can`'s, which
// documents them for the bus.
pub use perpend_can::status::{
    sensor_bits, sensor_nibble, CONFIG_INVALID, DEGRADED, NO_PLANE, RESIDUAL_HIGH, SENSOR_MASK,
    SENSOR_OPEN_LOOP, SENSOR_OUT_OF_RANGE, SENSOR_OVERCURRENT, SENSOR_STUCK, SENSOR_VALID,
    UNCALIBRATED,
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nibble_layout() {
        let s = sensor_bits(3, SENSOR_OVERCURRENT) | sensor_bits(1, SENSOR_VALID) | NO_PLANE;
        assert_eq!(s, 0x0008_8010);
        assert_eq!(sensor_nibble(s, 3), SENSOR_OVERCURRENT);
        assert_eq!(sensor_nibble(s, 1), SENSOR_VALID);
        assert_eq!(sensor_nibble(s, 0), 0);
        assert_eq!(sensor_bits(4, SENSOR_VALID), 0);
        assert_eq!(sensor_nibble(u32::MAX, 9), 0);
    }
}

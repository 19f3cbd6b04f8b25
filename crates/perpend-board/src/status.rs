//! The measurement status word (object 0x2005): bit constants.
//!
//! The contract is shared with `perpend-can` (its `status` module documents
//! the same layout):
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

/// Nibble bit: the sensor's reading is valid and used.
pub const SENSOR_VALID: u32 = 1 << 0;
/// Nibble bit: out of measuring range / saturated.
pub const SENSOR_OUT_OF_RANGE: u32 = 1 << 1;
/// Nibble bit: open loop (signal below the NE43 failure limit).
pub const SENSOR_OPEN_LOOP: u32 = 1 << 2;
/// Nibble bit: overcurrent (signal above the NE43 failure limit).
pub const SENSOR_OVERCURRENT: u32 = 1 << 3;
/// The four bits of one nibble.
pub const SENSOR_MASK: u32 = 0xF;
/// Plane from three sensors.
pub const DEGRADED: u32 = 1 << 16;
/// Factory calibration in use.
pub const UNCALIBRATED: u32 = 1 << 17;
/// Plane RMS residual above the limit.
pub const RESIDUAL_HIGH: u32 = 1 << 18;
/// No valid plane.
pub const NO_PLANE: u32 = 1 << 19;
/// At least one sensor is stuck.
pub const SENSOR_STUCK: u32 = 1 << 20;
/// The configuration is invalid.
pub const CONFIG_INVALID: u32 = 1 << 21;

/// `bits` (nibble bits) moved to sensor `i` (0-based); 0 for `i > 3`.
pub const fn sensor_bits(i: usize, bits: u32) -> u32 {
    if i < 4 {
        (bits & SENSOR_MASK) << (4 * i)
    } else {
        0
    }
}

/// The nibble of sensor `i` (0-based) in `status`; 0 for `i > 3`.
pub const fn sensor_nibble(status: u32, i: usize) -> u32 {
    if i < 4 {
        (status >> (4 * i)) & SENSOR_MASK
    } else {
        0
    }
}

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

//! The measurement status word (object 0x2005, UNSIGNED32) and the
//! emergency codes of the board: the contract between the board and the
//! robot controller.
//!
//! ```text
//! bit 4i+0  sensor i valid            (i = 0..3, sensor 1..4 on the bus)
//! bit 4i+1  sensor i out of range / saturated
//! bit 4i+2  sensor i open loop        (loop current below the NAMUR NE43 band)
//! bit 4i+3  sensor i overcurrent      (loop current above the band)
//! bit 16    degraded: plane from three sensors
//! bit 17    uncalibrated: calibration objects hold the nominal head
//! bit 18    plane RMS residual above 0x2300 sub 4
//! bit 19    no valid plane (fewer than three valid sensors, or degenerate)
//! bit 20    a sensor is stuck (reading constant beyond its noise)
//! bit 21    configuration invalid (e.g. a zero-length beam direction)
//! bits 22-31 reserved, 0
//! ```
//!
//! The normal (0x2001), angles (0x2002, 0x2003) and residual (0x2006) are
//! meaningful only when bit 19 is clear; while it is set they hold 0 (never
//! NaN: a zero normal is not a unit vector). The bits are the same as
//! `perpend_board::status`, which produces them.

/// Bit (within a sensor's nibble) set when the sensor's reading is valid.
pub const SENSOR_VALID: u32 = 1 << 0;
/// Bit (within a sensor's nibble): reading out of range or saturated.
pub const SENSOR_OUT_OF_RANGE: u32 = 1 << 1;
/// Bit (within a sensor's nibble): current loop open (below NE43 band).
pub const SENSOR_OPEN_LOOP: u32 = 1 << 2;
/// Bit (within a sensor's nibble): loop overcurrent (above NE43 band).
pub const SENSOR_OVERCURRENT: u32 = 1 << 3;
/// All four per-sensor bits of one nibble.
pub const SENSOR_MASK: u32 = 0xF;
/// Number of sensors the status word describes.
pub const SENSORS: usize = 4;

/// Degraded: the plane was fitted to three sensors.
pub const DEGRADED: u32 = 1 << 16;
/// The calibration objects hold the nominal (uncalibrated) head.
pub const UNCALIBRATED: u32 = 1 << 17;
/// The plane's RMS residual exceeds the limit of 0x2300 sub 4.
pub const RESIDUAL_HIGH: u32 = 1 << 18;
/// No valid plane: fewer than three valid sensors or degenerate spots.
pub const NO_PLANE: u32 = 1 << 19;
/// A sensor's reading is stuck at a constant.
pub const SENSOR_STUCK: u32 = 1 << 20;
/// The configuration or calibration in the object dictionary is invalid.
pub const CONFIG_INVALID: u32 = 1 << 21;

/// `bits` (a combination of the `SENSOR_*` nibble bits) shifted to sensor
/// `i` (0-based). Sensors beyond [`SENSORS`] give 0.
pub const fn sensor_bits(i: usize, bits: u32) -> u32 {
    if i < SENSORS {
        (bits & SENSOR_MASK) << (4 * i)
    } else {
        0
    }
}

/// The nibble of sensor `i` (0-based) in `status`.
pub const fn sensor_nibble(status: u32, i: usize) -> u32 {
    if i < SENSORS {
        (status >> (4 * i)) & SENSOR_MASK
    } else {
        0
    }
}

/// Emergency error codes (CiA 301 table 21 classes) the board produces.
/// [`crate::Device::publish`] raises and clears them from the status word;
/// manufacturer-specific data (5 bytes) is documented per code.
pub mod emcy {
    /// Sensor `i` (0-based) loop current outside the NE43 band (open loop
    /// or overcurrent): `0x2111 + i`, class 0x21xx "current, device input
    /// side". Data: `[sensor 1..4, its status nibble, 0, 0, 0]`. Error
    /// register: current.
    pub const fn sensor_current(i: usize) -> u16 {
        0x2111 + (i as u16 & 0xF)
    }
    /// Sensor `i` (0-based) reading not usable although its current is in
    /// band (out of range, saturated, stuck, jumped): `0xFF11 + i`, class
    /// 0xFFxx "device specific". Data: `[sensor 1..4, its status nibble,
    /// stuck 0/1, 0, 0]`. Error register: manufacturer specific.
    pub const fn sensor_reading(i: usize) -> u16 {
        0xFF11 + (i as u16 & 0xF)
    }
    /// No valid plane can be computed, class 0xFFxx. Data: `[number of
    /// valid sensors, 0, 0, 0, 0]`. Error register: manufacturer specific.
    pub const NO_PLANE: u16 = 0xFF02;
    /// The calibration/configuration is invalid (status bit 21) or a stored
    /// record was rejected at boot, class 0x63xx "data set". Error
    /// register: generic.
    pub const DATA_SET: u16 = 0x6300;
    /// CAN controller recovered from bus-off, class 0x81xx "communication".
    /// Error register: communication.
    pub const BUS_OFF_RECOVERED: u16 = 0x8140;
    /// CAN overrun, objects lost, class 0x81xx. Error register:
    /// communication. Data `[0, 0, 0, 0, 0]`: the receive FIFO lost
    /// frames; `[1, dropped (UNSIGNED32, little-endian)]`: the software
    /// transmit queue was full and dropped frames (the count since
    /// power-on, as in 0x2008 sub 1).
    pub const CAN_OVERRUN: u16 = 0x8110;
}

/// Bits of the error register (object 0x1001, CiA 301 table 47).
pub mod error_register {
    /// Generic error (set whenever any error is active).
    pub const GENERIC: u8 = 1 << 0;
    /// Current.
    pub const CURRENT: u8 = 1 << 1;
    /// Voltage.
    pub const VOLTAGE: u8 = 1 << 2;
    /// Temperature.
    pub const TEMPERATURE: u8 = 1 << 3;
    /// Communication error (overrun, error state).
    pub const COMMUNICATION: u8 = 1 << 4;
    /// Device profile specific.
    pub const PROFILE: u8 = 1 << 5;
    /// Manufacturer specific.
    pub const MANUFACTURER: u8 = 1 << 7;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nibbles_round_trip() {
        let s = sensor_bits(2, SENSOR_OPEN_LOOP) | sensor_bits(0, SENSOR_VALID) | DEGRADED;
        assert_eq!(s, 0x0001_0401);
        assert_eq!(sensor_nibble(s, 2), SENSOR_OPEN_LOOP);
        assert_eq!(sensor_nibble(s, 0), SENSOR_VALID);
        assert_eq!(sensor_nibble(s, 1), 0);
        assert_eq!(sensor_bits(4, SENSOR_VALID), 0);
        assert_eq!(sensor_nibble(s, 7), 0);
    }
}

//! The board's status word (0x2005), error register (0x1001) and
//! emergency codes in words, as docs/can.md defines them; an emergency
//! with the manufacturer bytes the board sends with it ([`emcy_text`]:
//! the two that 0x1003 keeps beside the code).

use perpend_can::status::{self, emcy};

/// One sensor's nibble in words.
pub fn sensor_words(nibble: u32) -> String {
    if nibble & status::SENSOR_VALID != 0 {
        return "valid".into();
    }
    let mut v = Vec::new();
    if nibble & status::SENSOR_OUT_OF_RANGE != 0 {
        v.push("out of range or saturated (no target in the measuring range?)");
    }
    if nibble & status::SENSOR_OPEN_LOOP != 0 {
        v.push("open loop: loop current below 3.6 mA (NAMUR NE43): cable or sensor supply");
    }
    if nibble & status::SENSOR_OVERCURRENT != 0 {
        v.push("overcurrent: loop current above 21 mA (short circuit or sensor fault)");
    }
    if v.is_empty() {
        v.push("not valid (stuck or jumped reading)");
    }
    v.join("; ")
}

/// The status word in words: one line per sensor, then one per flag.
pub fn status_words(st: u32, sensors: usize) -> Vec<String> {
    let mut out: Vec<String> = (0..sensors.min(status::SENSORS))
        .map(|i| {
            format!(
                "sensor {}: {}",
                i + 1,
                sensor_words(status::sensor_nibble(st, i))
            )
        })
        .collect();
    let flags: [(u32, &str); 6] = [
        (
            status::DEGRADED,
            "degraded: the plane comes from three sensors",
        ),
        (
            status::UNCALIBRATED,
            "uncalibrated: the calibration objects hold the factory head",
        ),
        (
            status::RESIDUAL_HIGH,
            "the plane's RMS residual is above the limit of 0x2300 sub 4",
        ),
        (
            status::NO_PLANE,
            "no valid plane: fewer than three valid sensors, degenerate spots or residual too \
             high (normal and angles read 0)",
        ),
        (
            status::SENSOR_STUCK,
            "a sensor is stuck (its reading constant beyond its noise)",
        ),
        (
            status::CONFIG_INVALID,
            "the configuration or calibration is invalid",
        ),
    ];
    out.extend(
        flags
            .iter()
            .filter(|(b, _)| st & b != 0)
            .map(|(_, s)| s.to_string()),
    );
    out
}

/// A one-line summary of the status word: `ok` or its problems, short.
pub fn status_short(st: u32, sensors: usize) -> String {
    let mut v = Vec::new();
    for i in 0..sensors.min(status::SENSORS) {
        let n = status::sensor_nibble(st, i);
        if n & status::SENSOR_VALID == 0 {
            let what = if n & status::SENSOR_OPEN_LOOP != 0 {
                "open loop"
            } else if n & status::SENSOR_OVERCURRENT != 0 {
                "overcurrent"
            } else if n & status::SENSOR_OUT_OF_RANGE != 0 {
                "out of range"
            } else {
                "invalid"
            };
            v.push(format!("s{} {what}", i + 1));
        }
    }
    for (b, s) in [
        (status::DEGRADED, "degraded"),
        (status::UNCALIBRATED, "uncalibrated"),
        (status::RESIDUAL_HIGH, "residual high"),
        (status::NO_PLANE, "NO PLANE"),
        (status::SENSOR_STUCK, "stuck"),
        (status::CONFIG_INVALID, "config invalid"),
    ] {
        if st & b != 0 {
            v.push(s.into());
        }
    }
    if v.is_empty() {
        "ok".into()
    } else {
        v.join(", ")
    }
}

/// An emergency code in words.
pub fn emcy_words(code: u16) -> String {
    for i in 0..status::SENSORS {
        if code == emcy::sensor_current(i) {
            return format!(
                "sensor {}: loop current outside the NE43 band (open loop or overcurrent)",
                i + 1
            );
        }
        if code == emcy::sensor_reading(i) {
            return format!(
                "sensor {}: reading unusable (out of range, stuck or jumped)",
                i + 1
            );
        }
    }
    match code {
        0 => "error reset: no error active any more".into(),
        emcy::NO_PLANE => "no valid plane".into(),
        emcy::DATA_SET => {
            "calibration or configuration invalid, or the stored record was rejected at boot".into()
        }
        emcy::BUS_OFF_RECOVERED => "the CAN controller recovered from bus-off".into(),
        emcy::CAN_OVERRUN => "CAN receive overrun: frames were lost".into(),
        perpend_can::device::EMCY_TABLE_FULL => {
            "more errors active than the board can list (the first one unlisted in the data)".into()
        }
        c => format!("{} (code {c:#06x})", emcy_class(c)),
    }
}

/// An emergency code in words with what its first two manufacturer bytes
/// say (`info`: bits 16-31 of its 0x1003 entry, byte 0 in the low 8
/// bits), as the board fills them: the 0x1F57 reason of a refused
/// firmware image, the sensor's state, the valid sensors, the node whose
/// heartbeat was lost, the SYNC length, which CAN queue lost frames.
pub fn emcy_text(code: u16, info: u16) -> String {
    let base = emcy_words(code);
    let [b0, b1] = info.to_le_bytes();
    let detail = match code {
        perpend_board::program::EMCY_PROGRAM_REFUSED => Some(format!(
            "firmware image refused: {} (0x1F57 = {info:#x})",
            super::update::flash_words(u32::from(info))
        )),
        perpend_board::health::EMCY_WATCHDOG_RESET => Some(format!(
            "watchdog reset (reset flags {b0:#04x}, 0x200B sub 1)"
        )),
        emcy::NO_PLANE => Some(format!("{base} ({b0} valid sensor(s))")),
        emcy::DATA_SET if b0 == 1 => Some(format!(
            "{base}: the stored record could not be read back (flash read faults)"
        )),
        emcy::CAN_OVERRUN if b0 == 1 => {
            Some("CAN transmit queue full: frames were dropped (count in 0x2008 sub 1)".to_string())
        }
        emcy::CAN_OVERRUN => Some("CAN receive overrun: received frames were lost".to_string()),
        perpend_can::device::EMCY_HEARTBEAT => Some(format!(
            "heartbeat of node {b0} lost (consumer 0x1016): communication error reaction 0x1029"
        )),
        perpend_can::device::EMCY_SYNC_LENGTH => Some(format!(
            "SYNC with {b0} data byte(s) ignored: its length does not match the SYNC counter \
             0x1019 (0: no data, 2..240: one byte)"
        )),
        perpend_can::device::EMCY_PDO_LENGTH => {
            Some("command RPDO without data (0x2500 needs one byte)".to_string())
        }
        c if (0..status::SENSORS)
            .any(|i| c == emcy::sensor_current(i) || c == emcy::sensor_reading(i))
            && (1..=status::SENSORS as u8).contains(&b0) =>
        {
            Some(format!(
                "sensor {b0}: {}",
                sensor_words(u32::from(b1) & status::SENSOR_MASK)
            ))
        }
        _ => None,
    };
    detail.unwrap_or(base)
}

/// The CiA 301 class of an emergency code.
fn emcy_class(code: u16) -> &'static str {
    match code >> 12 {
        0x1 => "generic error",
        0x2 => "current error",
        0x3 => "voltage error",
        0x4 => "temperature error",
        0x5 => "device hardware error",
        0x6 => "device software error",
        0x7 => "additional modules error",
        0x8 => "communication error",
        0x9 => "external error",
        0xF => "device-specific error",
        _ => "error",
    }
}

/// The error register (0x1001) in words.
pub fn error_register_words(reg: u8) -> String {
    use perpend_can::status::error_register as r;
    let names = [
        (r::GENERIC, "generic"),
        (r::CURRENT, "current"),
        (r::VOLTAGE, "voltage"),
        (r::TEMPERATURE, "temperature"),
        (r::COMMUNICATION, "communication"),
        (r::PROFILE, "device profile"),
        (r::MANUFACTURER, "manufacturer specific"),
    ];
    let v: Vec<&str> = names
        .iter()
        .filter(|(b, _)| reg & b != 0)
        .map(|(_, s)| *s)
        .collect();
    if v.is_empty() {
        "no error".into()
    } else {
        v.join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_words_name_each_problem() {
        let st = 0x1111 & !0x0010 | 0x0040 | status::DEGRADED;
        let w = status_words(st, 4);
        assert_eq!(w[0], "sensor 1: valid");
        assert!(w[1].starts_with("sensor 2: open loop"), "{}", w[1]);
        assert!(w[4].starts_with("degraded"));
        assert_eq!(status_short(st, 4), "s2 open loop, degraded");
        assert_eq!(status_short(0x1111, 4), "ok");
    }

    #[test]
    fn emcy_manufacturer_bytes_in_words() {
        use perpend_board::program::{EMCY_PROGRAM_REFUSED, FLASH_BAD_SIGNATURE};
        let t = emcy_text(EMCY_PROGRAM_REFUSED, FLASH_BAD_SIGNATURE as u16);
        assert!(
            t.starts_with("firmware image refused: the signature does not verify")
                && t.contains("0x1F57 = 0x82"),
            "{t}"
        );
        assert!(!t.contains("device software error"), "{t}");
        let t = emcy_text(emcy::sensor_current(1), u16::from_le_bytes([2, 0x04]));
        assert!(t.starts_with("sensor 2: open loop"), "{t}");
        assert_eq!(
            emcy_text(emcy::NO_PLANE, 2),
            "no valid plane (2 valid sensor(s))"
        );
        assert!(emcy_text(0x8130, 5).starts_with("heartbeat of node 5 lost"));
        assert!(emcy_text(emcy::CAN_OVERRUN, 1).contains("transmit queue"));
        assert_eq!(emcy_text(0x4210, 7), emcy_words(0x4210));
    }

    #[test]
    fn emcy_codes_in_words() {
        assert!(emcy_words(0x2112).starts_with("sensor 2: loop current"));
        assert!(emcy_words(0xFF14).starts_with("sensor 4: reading"));
        assert!(emcy_words(0x6100).starts_with("more errors active than"));
        assert_eq!(emcy_words(0xFF02), "no valid plane");
        assert!(emcy_words(0x4210).starts_with("temperature error"));
        assert_eq!(
            error_register_words(0x83),
            "generic, current, manufacturer specific"
        );
    }
}

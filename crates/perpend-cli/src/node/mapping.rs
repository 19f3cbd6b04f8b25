//! The board's PDOs in words, for `perpend node info`: every TPDO's and
//! RPDO's communication parameter (COB-ID, valid, transmission type,
//! inhibit time, event timer, SYNC start value) and mapping (CiA 301
//! §7.5.2.35-38, objects 0x1400/0x1600 and 0x1800/0x1A00), read from the
//! device itself, with each mapped object named and given its unit from
//! the board's dictionary ([`perpend_can::od`], the table the EDS is
//! written from).
//!
//! Units: the dictionary (like its EDS; CiA 306 has no unit key) carries a
//! unit only as the last word(s) of an object's name ("Theta1 deg",
//! "Distance sensor 1 mm"); [`split_unit`] takes them off. An object the
//! dictionary does not know (another firmware's mapping) is shown by its
//! index, sub-index and length.

use perpend_can::od;
use serde_json::{json, Value};

use super::Node;
use crate::canopen::pdo::{Mapped, Tpdo};
use crate::canopen::ClientError;

/// `name` split into its words and its unit as printed (`°C`, `°`, `µs`,
/// `mm/°C`, …), e.g. "Theta1 deg" → ("Theta1", Some("°")); the unit is
/// the one [`crate::eds::unit_of`] finds at the end of the name.
pub fn split_unit(name: &str) -> (&str, Option<String>) {
    let Some(unit) = crate::eds::unit_of(name) else {
        return (name, None);
    };
    // "mm/degC" was "mm per degC" (3 words), "1/mm" was "per mm" (2), else 1.
    let words = match unit.split_once('/') {
        Some(("1", _)) => 2,
        Some(_) => 3,
        None => 1,
    };
    let base = name.trim_end();
    let cut = base
        .rmatch_indices(' ')
        .nth(words - 1)
        .map_or(base.len(), |(i, _)| i);
    let pretty = |u: &str| match u {
        "degC" => "°C".to_string(),
        "deg" => "°".to_string(),
        "us" => "µs".to_string(),
        "ohm" => "Ω".to_string(),
        "mm2" => "mm²".to_string(),
        other => other.to_string(),
    };
    let shown = match unit.split_once('/') {
        Some((a, b)) => format!("{}/{}", pretty(a), pretty(b)),
        None => pretty(&unit),
    };
    (&base[..cut], Some(shown))
}

/// One mapped object in words: "Theta1 [°] (0x2002 sub 1)".
pub fn mapped_words(m: &Mapped) -> String {
    match od::find(m.index, m.sub) {
        Ok((_, e)) => match split_unit(e.name) {
            (n, Some(u)) => format!("{n} [{u}] ({:#06x} sub {})", m.index, m.sub),
            (n, None) => format!("{n} ({:#06x} sub {})", m.index, m.sub),
        },
        Err(_) => format!(
            "{:#06x} sub {} ({} bits, not in this dictionary)",
            m.index, m.sub, m.bits
        ),
    }
}

/// A transmission type in words (CiA 301 Table 72 for TPDOs; for RPDOs
/// 0..240 act at the next SYNC, 254/255 at once).
pub fn transmission_words(t: u8, transmit: bool) -> String {
    match (t, transmit) {
        (0, true) => "acyclic synchronous (at a SYNC after a change)".into(),
        (1, true) => "every SYNC".into(),
        (2..=240, true) => format!("every {} SYNC", ordinal(t)),
        (0..=240, false) => "acted on at the next SYNC".into(),
        (252 | 253, _) => format!("remote-request only ({t}, not supported here)"),
        (254 | 255, true) => format!("event-driven ({t})"),
        (254 | 255, false) => format!("acted on at once ({t})"),
        _ => format!("reserved ({t})"),
    }
}

/// `n` as an English ordinal: 2nd, 3rd, 11th, 21st.
fn ordinal(n: u8) -> String {
    let suffix = match (n % 10, n % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}

/// One PDO as JSON (also what the text is printed from).
fn pdo_json(kind: &str, t: &Tpdo, timing: (u32, u32, u32)) -> Value {
    let mapped: Vec<Value> = t
        .mapped
        .iter()
        .map(|m| {
            let (name, unit) = od::find(m.index, m.sub)
                .map(|(_, e)| split_unit(e.name))
                .map_or((None, None), |(n, u)| (Some(n), u));
            json!({"index": m.index, "sub": m.sub, "bits": m.bits,
                   "name": name, "unit": unit, "text": mapped_words(m)})
        })
        .collect();
    let transmit = kind == "TPDO";
    json!({
        "pdo": format!("{kind}{}", t.number), "cob_id": t.cob_id, "valid": t.valid,
        "transmission": t.transmission,
        "transmission_words": transmission_words(t.transmission, transmit),
        "inhibit_100us": timing.0, "event_timer_ms": timing.1, "sync_start": timing.2,
        "mapped": mapped,
    })
}

/// Reads the RPDO (0x1400/0x1600) parameters of `node`, as [`Tpdo`]
/// values (the same shape).
fn read_rpdo(node: &mut Node) -> Result<Tpdo, ClientError> {
    let (c, id) = (&mut node.client, node.id);
    let cob = c.read_u32(id, 0x1400, 1)?;
    let transmission = c.read_u32(id, 0x1400, 2)? as u8;
    let n = c.read_u32(id, 0x1600, 0)?.min(od::MAX_MAPPED as u32) as u8;
    let mut mapped = Vec::new();
    for s in 1..=n {
        mapped.push(Mapped::from_entry(c.read_u32(id, 0x1600, s)?));
    }
    Ok(Tpdo {
        number: 1,
        cob_id: (cob & 0x7FF) as u16,
        valid: cob & 0x8000_0000 == 0,
        transmission,
        mapped,
    })
}

/// Every PDO of the board as a JSON array (TPDO 1..4, then RPDO 1).
///
/// # Errors
/// Client errors.
pub fn read(node: &mut Node) -> Result<Value, ClientError> {
    let id = node.id;
    let tpdos = node.client.read_tpdos(id, od::TPDOS as u8)?;
    let mut out = Vec::new();
    for t in &tpdos {
        let k = t.number as u16 - 1;
        let inhibit = node.client.read_u32(id, 0x1800 + k, 3)?;
        let event = node.client.read_u32(id, 0x1800 + k, 5)?;
        let start = node.client.read_u32(id, 0x1800 + k, 6)?;
        out.push(pdo_json("TPDO", t, (inhibit, event, start)));
    }
    let r = read_rpdo(node)?;
    out.push(pdo_json("RPDO", &r, (0, 0, 0)));
    Ok(Value::Array(out))
}

/// The lines `info` prints for the PDOs of [`read`].
pub fn lines(pdos: &Value) -> Vec<String> {
    let mut out = Vec::new();
    for p in pdos.as_array().into_iter().flatten() {
        let name = p["pdo"].as_str().unwrap_or("?");
        let cob = p["cob_id"].as_u64().unwrap_or(0);
        if !p["valid"].as_bool().unwrap_or(false) {
            out.push(format!("{name:<6} {cob:#05x}  off (COB-ID bit 31 set)"));
            continue;
        }
        let mut timing = p["transmission_words"].as_str().unwrap_or("").to_string();
        let start = p["sync_start"].as_u64().unwrap_or(0);
        if start > 0 {
            timing += &format!(", from SYNC counter {start}");
        }
        match p["event_timer_ms"].as_u64().unwrap_or(0) {
            0 => {}
            ms => timing += &format!(", event timer {ms} ms"),
        }
        match p["inhibit_100us"].as_u64().unwrap_or(0) {
            0 => {}
            x => timing += &format!(", inhibit {:.1} ms", x as f64 / 10.0),
        }
        out.push(format!("{name:<6} {cob:#05x}  {timing}"));
        let mapped = p["mapped"].as_array().map_or(&[][..], |v| v.as_slice());
        if mapped.is_empty() {
            out.push("              (nothing mapped)".into());
        }
        for m in mapped {
            out.push(format!(
                "              {}",
                m["text"].as_str().unwrap_or("?")
            ));
        }
    }
    out
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn units_come_off_the_names() {
        let u = |n: &'static str| split_unit(n);
        let s = |x: &str| Some(x.to_string());
        assert_eq!(u("Theta1 deg"), ("Theta1", s("°")));
        assert_eq!(u("Distance sensor 1 mm"), ("Distance sensor 1", s("mm")));
        assert_eq!(
            u("Thermal drift mm per degC"),
            ("Thermal drift", s("mm/°C"))
        );
        assert_eq!(
            u("Cubic nonlinearity per mm2"),
            ("Cubic nonlinearity", s("1/mm²"))
        );
        assert_eq!(u("Die temperature degC"), ("Die temperature", s("°C")));
        assert_eq!(u("Sample counter"), ("Sample counter", None));
        // A word that merely ends in a unit's letters is not a unit.
        assert_eq!(u("Frames dropped"), ("Frames dropped", None));
    }

    #[test]
    fn every_mappable_object_has_words() {
        for o in od::OBJECTS {
            for e in o.subs.iter().filter(|e| e.pdo) {
                let m = Mapped {
                    index: o.index,
                    sub: e.sub,
                    bits: e.ty.bits(),
                };
                let w = mapped_words(&m);
                assert!(!w.contains("not in this dictionary"), "{w}");
                assert!(w.contains(&format!("{:#06x}", o.index)), "{w}");
            }
        }
        let w = mapped_words(&Mapped {
            index: 0x6000,
            sub: 1,
            bits: 16,
        });
        assert_eq!(w, "0x6000 sub 1 (16 bits, not in this dictionary)");
    }

    #[test]
    fn transmission_types_in_words() {
        assert_eq!(transmission_words(1, true), "every SYNC");
        assert_eq!(transmission_words(3, true), "every 3rd SYNC");
        assert_eq!(transmission_words(12, true), "every 12th SYNC");
        assert_eq!(transmission_words(22, true), "every 22nd SYNC");
        assert_eq!(transmission_words(255, true), "event-driven (255)");
        assert_eq!(transmission_words(255, false), "acted on at once (255)");
        assert_eq!(transmission_words(241, true), "reserved (241)");
    }
}

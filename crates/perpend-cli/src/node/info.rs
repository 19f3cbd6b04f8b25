//! `perpend node info`, `status` and `nmt`: what the board is (identity
//! 0x1018, device type 0x1000, name and versions 0x1008-0x100A, NMT state
//! from its heartbeat, node-id and bit rate 0x2400, acquisition 0x2300,
//! calibration lock 0x2010), how it is (status word 0x2005 in words, error
//! register 0x1001, the last emergencies from 0x1003), its PDOs in words
//! ([`super::mapping`]), die temperature (0x200A) and error register, and
//! NMT commands with their effect checked.
//!
//! The calibration stamp (0x2011: record hash, UTC seconds, store count) is
//! shown where the board's dictionary has it; a board whose firmware has
//! no such object (SDO abort 0x06020000) is said to have none.

use std::time::Duration;

use anyhow::Result;
use serde_json::json;

use super::words;
use super::{mapping, Node};
use crate::canopen::{ClientError, Nmt, NodeState};

/// The calibration stamp object (record hash, UTC seconds, store count).
pub const STAMP: u16 = 0x2011;
/// The board's time since boot [s].
pub const UPTIME: u16 = 0x200C;
/// The time after boot [s] at which each 0x1003 entry was recorded (same
/// sub-index).
pub const ERROR_TIMES: u16 = 0x2012;
/// SDO abort: object does not exist in the object dictionary.
const NO_OBJECT: u32 = 0x0602_0000;

/// Options of `info` and `status`.
#[derive(clap::Args, Debug)]
pub struct InfoArgs {
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Options of `nmt`.
#[derive(clap::Args, Debug)]
pub struct NmtArgs {
    /// The command.
    #[arg(value_enum)]
    pub command: Nmt,
}

fn state_text(s: Option<NodeState>, hb: u64) -> String {
    match (s, hb) {
        (_, 0) => "unknown (heartbeat off: 0x1017 = 0)".into(),
        (None, _) => format!("unknown (no heartbeat within {} ms)", hb * 3 / 2 + 200),
        (Some(s), _) => s.to_string(),
    }
}

/// Reads what `info` shows.
fn gather(node: &mut Node) -> Result<serde_json::Value> {
    let id = node.id;
    let device_type = node.hello()?;
    let c = &mut node.client;
    let name = c.read_string(id, 0x1008, 0)?;
    let hw = c.read_string(id, 0x1009, 0)?;
    let sw = c.read_string(id, 0x100A, 0)?;
    let active = c.read_u32(id, 0x1F56, 1).ok();
    let ident: Vec<u32> = (1..=4)
        .map(|s| c.read_u32(id, 0x1018, s))
        .collect::<Result<_, _>>()?;
    let stored_id = c.read_u32(id, 0x2400, 1)?;
    let kbps = c.read_u32(id, 0x2400, 2)?;
    let acq: Vec<u32> = (1..=3)
        .map(|s| c.read_u32(id, 0x2300, s))
        .collect::<Result<_, _>>()?;
    let limit = c.read_f32(id, 0x2300, 4)?;
    let unlocked = c.read_u32(id, 0x2010, 0)? != 0;
    let st = c.read_u32(id, 0x2005, 0)?;
    let reg = c.read_u32(id, 0x1001, 0)? as u8;
    let temp = c.read_f32(id, 0x200A, 0)?;
    let sensors = node.sensors()?;
    let hb = node.heartbeat_ms()?;
    let state = node.state(hb)?;
    let pdos = mapping::read(node)?;
    let stamp = read_stamp(node)?;
    let die_temp = (temp > perpend_can::od::DIE_TEMP_UNKNOWN).then_some(temp);
    Ok(json!({
        "node_id": id, "bus": node.client.bus_name(),
        "device_type": device_type, "device_name": name,
        "hardware_version": hw, "software_version": sw, "active_image": active,
        "vendor_id": ident[0], "product_code": ident[1],
        "revision": ident[2], "serial": ident[3],
        "heartbeat_ms": hb, "nmt_state": state_text(state, hb),
        "sensors": sensors, "stored_node_id": stored_id, "bit_rate_kbps": kbps,
        "sample_period_us": acq[0], "oversampling": acq[1],
        "plane_method": if acq[2] == 0 { "Chen" } else { "least squares" },
        "residual_limit_mm": limit, "calibration_unlocked": unlocked,
        "calibrated": st & perpend_can::status::UNCALIBRATED == 0,
        "error_register": reg, "error_register_words": words::error_register_words(reg),
        "die_temp_c": die_temp, "calibration_stamp": stamp, "pdos": pdos,
    }))
}

/// The calibration stamp (0x2011) as JSON, `null` when the board's
/// dictionary has no such object.
fn read_stamp(node: &mut Node) -> Result<serde_json::Value> {
    let (c, id) = (&mut node.client, node.id);
    let hash = match c.read_u32(id, STAMP, 1) {
        Ok(h) => h,
        Err(ClientError::Abort {
            code: NO_OBJECT, ..
        }) => return Ok(serde_json::Value::Null),
        Err(e) => return Err(e.into()),
    };
    let utc = c.read_u32(id, STAMP, 2)?;
    let count = c.read_u32(id, STAMP, 3)?;
    Ok(json!({"record_hash": format!("{hash:08x}"), "utc_s": utc, "store_count": count}))
}

/// `perpend node info`.
///
/// # Errors
/// Client errors, in sentences.
pub fn info(node: &mut Node, a: &InfoArgs) -> Result<()> {
    let v = gather(node)?;
    if a.json {
        println!("{}", crate::schema::tagged(crate::schema::NODE_INFO, &v));
        return Ok(());
    }
    let s = |k: &str| v[k].as_str().unwrap_or("").to_string();
    let u = |k: &str| v[k].as_u64().unwrap_or(0);
    let rev = u("revision");
    println!("{}", node.name());
    println!(
        "  device        {} (hardware {}, software {}), device type {:#010x}",
        s("device_name"),
        s("hardware_version"),
        s("software_version"),
        u("device_type")
    );
    println!(
        "  identity      vendor {:#010x}, product {:#010x}, revision {}.{} ({rev:#010x})",
        u("vendor_id"),
        u("product_code"),
        rev >> 16,
        rev & 0xFFFF
    );
    println!("  serial        {:#010x}", u("serial"));
    let image = v["active_image"]
        .as_u64()
        .map(|i| super::update::version_words(i as u32));
    println!(
        "  active image  {} (0x1F56)",
        image.as_deref().unwrap_or("not reported")
    );
    println!(
        "  NMT state     {} (heartbeat every {} ms)",
        s("nmt_state"),
        u("heartbeat_ms")
    );
    print_config(&v);
    print_health(&v);
    println!("  PDOs");
    for l in mapping::lines(&v["pdos"]) {
        println!("    {l}");
    }
    Ok(())
}

/// The stamp, temperature and error register lines of `info`.
fn print_health(v: &serde_json::Value) {
    let st = &v["calibration_stamp"];
    if st.is_null() {
        println!(
            "  stamp         none: this firmware has no calibration stamp object ({STAMP:#06x})"
        );
    } else if st["utc_s"].as_u64() == Some(0) {
        println!("  stamp         none stored (the calibration was never pushed with a record)");
    } else {
        let hash = st["record_hash"].as_str().unwrap_or("?");
        println!(
            "  stamp         record {hash} stored {} (store #{}); its record: perpend record \
             find {hash} DIR",
            utc_words(st["utc_s"].as_u64().unwrap_or(0)),
            st["store_count"].as_u64().unwrap_or(0)
        );
    }
    match v["die_temp_c"].as_f64() {
        Some(t) => println!("  die temp      {t:.1} °C (0x200A)"),
        None => println!(
            "  die temp      not measured (0x200A reads {} °C)",
            perpend_can::od::DIE_TEMP_UNKNOWN
        ),
    }
    println!(
        "  error reg.    {:#04x}: {}",
        v["error_register"].as_u64().unwrap_or(0),
        v["error_register_words"].as_str().unwrap_or("")
    );
}

/// UTC seconds since 1970 as ISO 8601 (`2026-11-27T10:58:43Z`).
pub fn utc_words(secs: u64) -> String {
    let t = std::time::UNIX_EPOCH + Duration::from_secs(secs);
    humantime::format_rfc3339_seconds(t).to_string()
}
/// The head, lock, acquisition and CAN lines of `info`.
fn print_config(v: &serde_json::Value) {
    let s = |k: &str| v[k].as_str().unwrap_or("").to_string();
    let u = |k: &str| v[k].as_u64().unwrap_or(0);
    let b = |k: &str| v[k].as_bool().unwrap_or(false);
    println!(
        "  head          {} sensors, {}",
        u("sensors"),
        if b("calibrated") {
            "calibrated"
        } else {
            "uncalibrated (factory head)"
        }
    );
    println!(
        "  calibration   {}",
        if b("calibration_unlocked") {
            "UNLOCKED (0x2010): a write is in progress or was left open"
        } else {
            "locked"
        }
    );
    println!(
        "  acquisition   every {} µs, oversampling {}, plane method {}, residual limit {} mm",
        u("sample_period_us"),
        u("oversampling"),
        s("plane_method"),
        v["residual_limit_mm"].as_f64().unwrap_or(f64::NAN) as f32
    );
    println!(
        "  stored CAN    node-id {}, {} kbit/s (0x2400, effective after a reset)",
        u("stored_node_id"),
        u("bit_rate_kbps")
    );
}

/// The board's uptime (0x200C) and the time after boot at which each of
/// the first `n` 0x1003 entries was recorded (0x2012), in seconds; `None`
/// on a firmware without these objects.
fn error_times(node: &mut Node, n: u8) -> Result<Option<(u32, Vec<u32>)>> {
    let (c, id) = (&mut node.client, node.id);
    let up = match c.read_u32(id, UPTIME, 0) {
        Ok(u) => u,
        Err(ClientError::Abort {
            code: NO_OBJECT, ..
        }) => return Ok(None),
        Err(e) => return Err(e.into()),
    };
    let mut at = Vec::new();
    for s in 1..=n {
        at.push(c.read_u32(id, ERROR_TIMES, s)?);
    }
    Ok(Some((up, at)))
}

/// An age in words: `42 s`, `3 min 5 s`, `2 h 10 min`, `3 d 4 h`.
pub fn age_words(s: u32) -> String {
    match s {
        0..=59 => format!("{s} s"),
        60..=3599 => format!("{} min {} s", s / 60, s % 60),
        3600..=86_399 => format!("{} h {} min", s / 3600, s / 60 % 60),
        _ => format!("{} d {} h", s / 86_400, s / 3600 % 24),
    }
}

/// `perpend node status`: the status word in words, the error register,
/// and the emergency history (0x1003) with each entry's time after boot
/// and age (0x2012 against the uptime 0x200C), so that an old emergency
/// is not taken for a present one (the history starts empty at boot, so
/// every entry has a time; a firmware without 0x200C/0x2012 shows none).
///
/// # Errors
/// Client errors, in sentences.
pub fn status(node: &mut Node, a: &InfoArgs) -> Result<()> {
    let id = node.id;
    node.hello()?;
    let sensors = node.sensors()?;
    let c = &mut node.client;
    let st = c.read_u32(id, 0x2005, 0)?;
    let sample = c.read_u32(id, 0x2007, 0)?;
    let reg = c.read_u32(id, 0x1001, 0)? as u8;
    let n = c.read_u32(id, 0x1003, 0)?.min(8) as u8;
    let mut errors = Vec::new();
    for s in 1..=n {
        let v = c.read_u32(id, 0x1003, s)?;
        errors.push(((v & 0xFFFF) as u16, (v >> 16) as u16));
    }
    let times = error_times(node, n)?;
    let age = |k: usize| {
        times
            .as_ref()
            .map(|(up, at)| (at[k], up.saturating_sub(at[k])))
    };
    if a.json {
        let e: Vec<_> = errors
            .iter()
            .enumerate()
            .map(|(k, (code, info))| {
                json!({"code": code, "info": info, "text": words::emcy_text(*code, *info),
                       "at_s": age(k).map(|x| x.0), "age_s": age(k).map(|x| x.1)})
            })
            .collect();
        let v = json!({
            "node_id": id, "status": st, "sample": sample,
            "status_words": words::status_words(st, sensors),
            "error_register": reg, "uptime_s": times.as_ref().map(|t| t.0), "errors": e,
        });
        println!("{}", crate::schema::tagged(crate::schema::NODE_STATUS, &v));
        return Ok(());
    }
    println!("{}: status {st:#010x} at sample {sample}", node.name());
    for w in words::status_words(st, sensors) {
        println!("  {w}");
    }
    println!(
        "error register {reg:#04x}: {}",
        words::error_register_words(reg)
    );
    print_history(&errors, times.as_ref());
    Ok(())
}

/// The emergency history lines of `status`.
fn print_history(errors: &[(u16, u16)], times: Option<&(u32, Vec<u32>)>) {
    if errors.is_empty() {
        println!("no emergency recorded (0x1003 is empty)");
        return;
    }
    match times {
        Some((up, _)) => println!(
            "last emergencies (0x1003, newest first; up {}; `clear-errors` empties the list):",
            age_words(*up)
        ),
        None => {
            println!("last emergencies (0x1003, newest first; this firmware records no times):")
        }
    }
    for (k, (code, info)) in errors.iter().enumerate() {
        match times {
            Some((up, at)) => println!(
                "  {code:#06x}  {:>14}  {}",
                format!("{} ago", age_words(up.saturating_sub(at[k]))),
                words::emcy_text(*code, *info)
            ),
            None => println!("  {code:#06x}  {}", words::emcy_text(*code, *info)),
        }
    }
}

/// `perpend node clear-errors`: writes 0 to 0x1003 sub 0 (CiA 301
/// §7.5.2.4: the only value allowed, it empties the history) and says
/// what is left: errors still active stay in the error register (0x1001)
/// and come back into the history with their next EMCY.
///
/// # Errors
/// Client errors; a history that is not empty after the write.
pub fn clear_errors(node: &mut Node, a: &InfoArgs) -> Result<()> {
    let id = node.id;
    node.hello()?;
    let c = &mut node.client;
    let before = c.read_u32(id, 0x1003, 0)?;
    c.download(id, 0x1003, 0, &[0])?;
    let after = c.read_u32(id, 0x1003, 0)?;
    let reg = c.read_u32(id, 0x1001, 0)? as u8;
    if after != 0 {
        anyhow::bail!(
            "{}: 0x1003 still lists {after} emergencies after it was cleared",
            node.name()
        );
    }
    if a.json {
        let v = json!({"node_id": id, "cleared": before, "error_register": reg,
                       "error_register_words": words::error_register_words(reg)});
        println!("{}", crate::schema::tagged(crate::schema::CLEAR_ERRORS, &v));
        return Ok(());
    }
    println!(
        "{}: emergency history cleared ({before} entries removed from 0x1003)",
        node.name()
    );
    if reg != 0 {
        println!(
            "  still active (error register {reg:#04x}): {}; their cause is still there",
            words::error_register_words(reg)
        );
    }
    Ok(())
}

/// `perpend node nmt`: sends the command and checks its effect (a boot-up
/// after a reset, else the next heartbeat's state).
///
/// # Errors
/// No boot-up, or a heartbeat that shows another state.
pub fn nmt(node: &mut Node, a: &NmtArgs) -> Result<()> {
    let id = node.id;
    node.client.nmt(id, a.command)?;
    if matches!(a.command, Nmt::Reset | Nmt::ResetComm) {
        node.client.wait_bootup(id, Duration::from_secs(5))?;
        println!("{}: reset, boot-up received (pre-operational)", node.name());
        return Ok(());
    }
    let want = match a.command {
        Nmt::Start => NodeState::Operational,
        Nmt::Stop => NodeState::Stopped,
        _ => NodeState::PreOperational,
    };
    // The heartbeat period cannot be read from a stopped node: wait for
    // up to 3 s of heartbeats instead.
    let end = std::time::Instant::now() + Duration::from_secs(3);
    while let Some(left) = end.checked_duration_since(std::time::Instant::now()) {
        match node.client.wait_heartbeat(id, left)? {
            Some(s) if s == want => {
                println!("{}: {want}", node.name());
                return Ok(());
            }
            Some(_) => {}
            None => break,
        }
    }
    println!(
        "{}: {} sent; no heartbeat confirmed it within 3 s (heartbeat off?)",
        node.name(),
        want
    );
    Ok(())
}

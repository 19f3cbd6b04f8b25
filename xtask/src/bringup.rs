//! `cargo xtask bring-up --bus BUS --node-id N` | `cargo xtask bring-up
//! --virtual`: the bus side of `docs/bring-up.md` against a board (or a
//! virtual board it starts), through the `perpend node` commands (the
//! project's CANopen client): one line per check, `PASS`/`FAIL` with what
//! was expected and what was seen, and a last line `bring-up: N passed, M
//! failed`. Exit code 1 when a check failed.
//!
//! Checks (the step numbers of docs/bring-up.md):
//! * B1 identity (`node info --json`): the node answers SDO, device name
//!   "perpend…", a serial number (0x1018 sub 4) other than 0, 4 sensors, a
//!   heartbeat heard (NMT state known);
//! * B2 acquisition (`node status --json` twice, ≥ 0.5 s apart): the sample
//!   counter 0x2007 advances at 1/period (0x2300 sub 1) within 20 %;
//! * B3 inputs: every sensor's status nibble is "valid" (4-20 mA in band,
//!   reading in range);
//! * B4 errors: no watchdog reset (EMCY 0x6010) and no stored-record or ECC
//!   problem (EMCY 0x6300) in the error history 0x1003;
//! * B5 TPDOs (`node monitor --start --seconds 2 --sync-hz 100 --csv`):
//!   at least 150 of the 200 SYNCs answered by a row.
//!
//! The checks on the JSON are pure functions ([`check_info`],
//! [`check_rate`], [`check_sensors`], [`check_errors`]), unit-tested here;
//! the whole run is tested against the virtual board.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;

use crate::{cargo, root, run, Result};

/// One check's outcome.
#[derive(Debug, Clone, PartialEq)]
pub struct Check {
    /// Step id (B1..B5).
    pub id: &'static str,
    /// Passed.
    pub ok: bool,
    /// Expected and seen, in words.
    pub text: String,
}

fn check(id: &'static str, ok: bool, text: String) -> Check {
    Check { id, ok, text }
}

/// B1 on `node info --json`.
pub fn check_info(v: &Value) -> Check {
    let name = v["device_name"].as_str().unwrap_or("");
    let serial = v["serial"].as_u64().unwrap_or(0);
    let sensors = v["sensors"].as_u64().unwrap_or(0);
    let state = v["nmt_state"].as_str().unwrap_or("unknown");
    let ok =
        name.starts_with("perpend") && serial != 0 && sensors == 4 && !state.starts_with("unknown");
    check(
        "B1",
        ok,
        format!(
            "identity: expected device 'perpend…', serial ≠ 0, 4 sensors, heartbeat; seen '{name}', serial {serial:#010x}, {sensors} sensors, NMT {state}, {} kbit/s, firmware {}",
            v["bit_rate_kbps"], v["software_version"]
        ),
    )
}

/// B2: the sample counter advanced by `d_samples` in `dt_s` at a period of
/// `period_us`.
pub fn check_rate(d_samples: i64, dt_s: f64, period_us: f64) -> Check {
    let want = dt_s * 1e6 / period_us;
    let ok = d_samples > 0 && (d_samples as f64 - want).abs() <= 0.2 * want;
    check(
        "B2",
        ok,
        format!(
            "acquisition: expected ≈ {want:.0} samples in {dt_s:.2} s (period {period_us} µs), seen {d_samples}"
        ),
    )
}

/// B3 on `node status --json`: the status words of the four sensors.
pub fn check_sensors(v: &Value) -> Check {
    let st = v["status"].as_u64().unwrap_or(0) as u32;
    let bad: Vec<String> = (0..4)
        .filter(|i| (st >> (4 * i)) & 0xF != 1)
        .map(|i| format!("sensor {} nibble {:#x}", i + 1, (st >> (4 * i)) & 0xF))
        .collect();
    let words: Vec<String> = v["status_words"]
        .as_array()
        .map(|a| {
            a.iter()
                .filter_map(|w| w.as_str().map(str::to_string))
                .collect()
        })
        .unwrap_or_default();
    check(
        "B3",
        bad.is_empty(),
        format!(
            "inputs: expected 4 valid sensors (nibble 0x1: 4-20 mA in band, reading in range); status {st:#010x}{}{}",
            if bad.is_empty() { String::new() } else { format!(", {}", bad.join(", ")) },
            if words.is_empty() { String::new() } else { format!(" ({})", words.join("; ")) }
        ),
    )
}

/// B4 on `node status --json`: the error history.
pub fn check_errors(v: &Value) -> Check {
    let codes: Vec<u64> = v["errors"]
        .as_array()
        .map(|a| a.iter().filter_map(|e| e["code"].as_u64()).collect())
        .unwrap_or_default();
    let bad: Vec<String> = codes
        .iter()
        .filter(|c| matches!(c, 0x6010 | 0x6300))
        .map(|c| match c {
            0x6010 => "0x6010 watchdog reset".to_string(),
            _ => "0x6300 stored record rejected or unreadable (ECC)".to_string(),
        })
        .collect();
    check(
        "B4",
        bad.is_empty(),
        format!(
            "errors: expected no 0x6010/0x6300 in 0x1003; seen {} entr{} {:x?}{}",
            codes.len(),
            if codes.len() == 1 { "y" } else { "ies" },
            codes,
            if bad.is_empty() {
                String::new()
            } else {
                format!(": {}", bad.join(", "))
            }
        ),
    )
}

fn perpend_bin() -> PathBuf {
    crate::cell::perpend()
}

/// `perpend node --bus BUS --node-id N ARGS`: its stdout.
fn node(bus: &str, id: &str, args: &[&str]) -> Result<String> {
    let out = Command::new(perpend_bin())
        .args(["--quiet", "node", "--bus", bus, "--node-id", id])
        .args(args)
        .stderr(Stdio::inherit())
        .output()
        .map_err(|e| format!("perpend: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "perpend node {} failed ({})",
            args.join(" "),
            out.status
        ));
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

fn json(s: &str) -> Result<Value> {
    serde_json::from_str(s.trim()).map_err(|e| format!("not JSON ({e}): {s}"))
}

/// Runs B1..B5 against `bus`/`id`; `dir` takes the monitor log.
pub fn checks(bus: &str, id: &str, dir: &Path) -> Result<Vec<Check>> {
    let info = json(&node(bus, id, &["info", "--json"])?)?;
    let mut out = vec![check_info(&info)];
    let t0 = Instant::now();
    let s0 = json(&node(bus, id, &["status", "--json"])?)?;
    std::thread::sleep(Duration::from_millis(500));
    let s1 = json(&node(bus, id, &["status", "--json"])?)?;
    let dt = t0.elapsed().as_secs_f64();
    let d = s1["sample"].as_i64().unwrap_or(0) - s0["sample"].as_i64().unwrap_or(0);
    let period = info["sample_period_us"].as_f64().unwrap_or(1000.0);
    // the two reads are dt apart only up to their own SDO round trips
    out.push(check_rate(d, dt, period));
    out.push(check_sensors(&s1));
    out.push(check_errors(&s1));
    let csv = dir.join("bring-up-monitor.csv");
    let csv_s = csv.to_string_lossy().into_owned();
    node(
        bus,
        id,
        &[
            "monitor",
            "--start",
            "--seconds",
            "2",
            "--sync-hz",
            "100",
            "--csv",
            &csv_s,
        ],
    )?;
    let rows = std::fs::read_to_string(&csv)
        .map(|t| t.lines().count().saturating_sub(1))
        .unwrap_or(0);
    out.push(check(
        "B5",
        rows >= 150,
        format!("TPDOs: expected ≥ 150 rows for 200 SYNC at 100 Hz, seen {rows} ({csv_s})"),
    ));
    Ok(out)
}

/// Starts `perpend board` on a free loopback port; returns it and its bus.
fn virtual_board() -> Result<(crate::cell::Stopped, String)> {
    let args = [
        "board",
        "--slcan",
        "127.0.0.1:0",
        "--node-id",
        "16",
        "--plane",
        "0,0,1,-40",
    ];
    let (child, a) = crate::cell::spawn_board(&root(), &args, 1)?;
    let bus = a.first().ok_or("perpend board: no bus address")?;
    Ok((child, format!("tcp:{bus}")))
}

/// `cargo xtask bring-up`.
pub fn bring_up(args: &[String]) -> Result<()> {
    let get = |k: &str| {
        args.iter()
            .position(|a| a == k)
            .and_then(|i| args.get(i + 1))
            .cloned()
    };
    run(&cargo(), &["build", "--quiet", "-p", "perpend-cli"])?;
    let dir = root().join("target").join("bring-up");
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let (_board, bus, id) = if args.iter().any(|a| a == "--virtual") {
        let (b, bus) = virtual_board()?;
        (Some(b), bus, "16".to_string())
    } else {
        let bus =
            get("--bus").ok_or("usage: cargo xtask bring-up --bus BUS --node-id N | --virtual")?;
        (None, bus, get("--node-id").unwrap_or_else(|| "16".into()))
    };
    let res = checks(&bus, &id, &dir)?;
    let failed = res.iter().filter(|c| !c.ok).count();
    for c in &res {
        println!(
            "{} {}: {}",
            if c.ok { "PASS" } else { "FAIL" },
            c.id,
            c.text
        );
    }
    println!("bring-up: {} passed, {failed} failed", res.len() - failed);
    if failed == 0 {
        Ok(())
    } else {
        Err(format!(
            "{failed} bring-up check(s) failed: see docs/bring-up.md"
        ))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn identity_needs_a_serial_and_four_sensors() {
        let good = json!({"device_name": "perpend normal sensor", "serial": 0x1234u32,
            "sensors": 4, "nmt_state": "pre-operational", "bit_rate_kbps": 1000, "software_version": "0.1.0"});
        assert!(check_info(&good).ok);
        let mut v = good.clone();
        v["serial"] = json!(0);
        assert!(!check_info(&v).ok);
        let mut v = good.clone();
        v["nmt_state"] = json!("unknown (no heartbeat within 1700 ms)");
        assert!(!check_info(&v).ok);
        let mut v = good;
        v["sensors"] = json!(3);
        assert!(!check_info(&v).ok);
    }

    #[test]
    fn rate_within_twenty_percent() {
        assert!(check_rate(500, 0.5, 1000.0).ok);
        assert!(check_rate(590, 0.5, 1000.0).ok);
        assert!(!check_rate(620, 0.5, 1000.0).ok);
        assert!(!check_rate(0, 0.5, 1000.0).ok);
        assert!(!check_rate(-3, 0.5, 1000.0).ok);
    }

    #[test]
    fn sensors_and_errors() {
        assert!(check_sensors(&json!({"status": 0x1111, "status_words": []})).ok);
        let c = check_sensors(&json!({"status": 0x000A_1411u32}));
        assert!(
            !c.ok
                && !c.text.contains("sensor 2 nibble 0x1")
                && c.text.contains("sensor 3 nibble 0x4"),
            "{}",
            c.text
        );
        assert!(check_errors(&json!({"errors": [{"code": 0x8110}]})).ok);
        let c = check_errors(&json!({"errors": [{"code": 0x6010}, {"code": 0x2111}]}));
        assert!(!c.ok && c.text.contains("watchdog"), "{}", c.text);
        assert!(!check_errors(&json!({"errors": [{"code": 0x6300}]})).ok);
    }

    /// The whole bring-up against the virtual board (builds `perpend`).
    #[test]
    fn bring_up_passes_on_the_virtual_board() {
        // `cargo xtask test` built it with the tests (PERPEND_BIN); a
        // `cargo build -p perpend-cli` would resolve other features and
        // build it again.
        if std::env::var_os("PERPEND_BIN").is_none() {
            run(&cargo(), &["build", "--quiet", "-p", "perpend-cli"]).unwrap();
        }
        let (_b, bus) = virtual_board().unwrap();
        let dir = tempdir();
        let res = checks(&bus, "16", &dir).unwrap();
        for c in &res {
            eprintln!("{} {} {}", c.ok, c.id, c.text);
        }
        assert_eq!(res.len(), 5);
        assert!(res.iter().all(|c| c.ok), "{res:#?}");
    }

    fn tempdir() -> PathBuf {
        let d = std::env::temp_dir().join(format!("perpend-bring-up-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }
}

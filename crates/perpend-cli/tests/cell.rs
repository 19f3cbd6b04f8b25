//! `perpend cell run` end to end: a virtual board whose true head is the
//! paper's (Chen Table 2 errors) while it stores the nominal one, a
//! simulated robot (its world channel) and tracker; the script measures
//! before, captures the planned poses over slcan/TCP, calibrates, pushes,
//! resets and measures again on fresh poses. Bounded in time; the board is
//! killed at the end, also on failure. The poses are around the paper's
//! orientation (θ1 17.89°, θ2 −1.04°), 34-37 mm standoff so that every
//! reading stays inside the board's 20-80 mm range.
#![allow(clippy::unwrap_used, clippy::panic)]

mod common;

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{board, Killed, BIN};

#[test]
fn a_cell_calibration_reaches_the_floor_over_the_bus() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::head_and_plan(d, 16);
    let (_board, bus, world) = board(d, "truth.csv", &[]);
    let mut run = Killed(
        Command::new(BIN)
            .args(["--quiet", "cell", "run", "--node-id", "16"])
            .args(["--bus", &format!("tcp:{bus}")])
            .args(["--robot", &format!("sim:{world}")])
            .args(["--sensors", "nominal.csv", "--plan", "plan.csv"])
            .args(["--truth", "truth.csv", "--out", "run"])
            .current_dir(d)
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let start = Instant::now();
    let status = loop {
        if let Some(s) = run.0.try_wait().unwrap() {
            break s;
        }
        assert!(start.elapsed() < Duration::from_secs(180), "cell run hung");
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut err = String::new();
    if let Some(mut e) = run.0.stderr.take() {
        let _ = std::io::Read::read_to_string(&mut e, &mut err);
    }
    assert!(status.success(), "{err}");
    let text = std::fs::read_to_string(d.join("run/cell.json")).unwrap();
    assert!(
        text.starts_with("{\n  \"schema\": \"perpend.cell/1\","),
        "{text}"
    );
    let f: serde_json::Value = serde_json::from_str(&text).unwrap();
    let g = |k: &str| f[k].as_f64().unwrap();
    // The paper's orientation (Chen Table 1 plane): about 1.3-1.7° before.
    assert!((0.8..3.0).contains(&g("before_deg")), "{text}");
    assert!(g("after_deg") <= 1.2 * g("floor_deg"), "{text}");
    assert!(g("floor_deg") > 0.0 && g("floor_deg") < 0.05, "{text}");
    assert_eq!(f["poses"], 16);
    assert_eq!(f["outcome"], "kept", "{text}");
    // The board holds what was pushed; previous.json what it held before.
    let state = common::board_state(d, &bus, "run");
    let new = common::calibration(d, "run/params.json");
    assert!(common::same_geometry(&state.sensors, &new), "{state:?}");
    assert_eq!(common::geometry(&state.sensors).len(), 24);
    let previous = common::calibration(d, "run/previous.json");
    assert!(!common::same_geometry(&state.sensors, &previous));
    common::as_found(&state, "pre-operational");
    // The record: inputs hashed, the board's serial and firmware, the
    // fresh-pose verification after the push (its mean is cell.json's
    // after figure), the previous calibration, what the run did.
    let rec_text = std::fs::read_to_string(d.join("run/record.json")).unwrap();
    let rec: serde_json::Value = serde_json::from_str(&rec_text).unwrap();
    assert_eq!(rec["schema"], "perpend.record/1");
    let inputs: Vec<&str> = rec["inputs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["path"].as_str().unwrap())
        .collect();
    for want in ["nominal.csv", "poses.csv", "plan.csv"] {
        assert!(inputs.iter().any(|p| p.ends_with(want)), "{inputs:?}");
    }
    assert!(rec["head_serial"].as_str().unwrap().starts_with("0x"));
    assert!(rec["firmware"].as_str().unwrap().starts_with("perpend"));
    let v = &rec["verification"];
    assert_eq!(v["kind"], "fresh poses");
    assert_eq!(
        v["poses"].as_array().unwrap().len(),
        f["verify_poses"].as_u64().unwrap() as usize
    );
    // Per-pose means of equal sample counts: their mean is the overall one.
    assert!(
        (v["mean_deg"].as_f64().unwrap() - g("after_deg")).abs() < 1e-9,
        "{rec_text}"
    );
    assert_eq!(v["expected_deg"].as_f64().unwrap(), g("expected_deg"));
    assert!(
        rec["previous"]["params_sha256"].as_str().is_some(),
        "{rec_text}"
    );
    let events = rec["events"].as_array().unwrap();
    assert!(
        events
            .iter()
            .any(|e| e.as_str().unwrap().contains("perpend cell run: kept")),
        "{rec_text}"
    );
    let cert = std::fs::read_to_string(d.join("run/cert.html")).unwrap();
    assert!(
        cert.contains(rec["head_serial"].as_str().unwrap()),
        "cert without the serial"
    );
    // The board carries the stamp of the calibration's record.
    let link = ["node", "--bus", &format!("tcp:{bus}"), "--node-id", "16"];
    let info: serde_json::Value =
        serde_json::from_str(&common::ok(&[&link[..], &["info", "--json"]].concat(), d)).unwrap();
    let stamp = &info["calibration_stamp"];
    let rec_hash =
        perpend_lab::record::sha256_hex(&std::fs::read(d.join("run/params.record.json")).unwrap());
    assert_eq!(
        stamp["record_hash"].as_str().unwrap(),
        &rec_hash[..8],
        "{info}"
    );
    assert!(stamp["store_count"].as_u64().unwrap() >= 1);
}

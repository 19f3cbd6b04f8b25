//! `perpend cell run --reversal` end to end on the virtual board (issue 36
//! item 5): the board's world tilts the tracker by 0.05° about x
//! (`--tracker-tilt-deg 0.05`), the plan turns every pose to
//! 0/90/180/270° about the spindle axis; the run estimates the tilt within
//! 0.005°, its after error against the true planes is within 1.2× the
//! floor, and the record carries the estimate. Bounded in time; the board
//! is killed at the end, also on failure.
#![allow(clippy::unwrap_used, clippy::panic)]

mod common;

use std::process::{Command, Stdio};

use common::{board, Killed, BIN};

fn reversal_plan(d: &std::path::Path) {
    common::ok(&["cell", "sim-head", "--out", "."], d);
    common::ok(
        &[
            "plan",
            "--sensors",
            "nominal.csv",
            "--n",
            "12",
            "--tilt-max",
            "8",
            "--standoff",
            "34,37",
            "--draws",
            "2",
            "--reversal",
            "4",
            "--out",
            "plan.csv",
        ],
        d,
    );
}

#[test]
fn reversal_finds_a_tilted_tracker_and_the_head_reaches_the_floor() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    reversal_plan(d);
    let (_board, bus, world) = board(d, "truth.csv", &["--tracker-tilt-deg", "0.05,0"]);
    let run = Killed(
        Command::new(BIN)
            .args(["--quiet", "cell", "run", "--node-id", "16", "--reversal"])
            .args(["--bus", &format!("tcp:{bus}")])
            .args(["--robot", &format!("sim:{world}")])
            .args(["--sensors", "nominal.csv", "--plan", "plan.csv"])
            .args(["--truth", "truth.csv", "--out", "run", "--samples", "20"])
            .current_dir(d)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let (status, out, err) = common::finish(run, 300);
    assert!(status.success(), "{out}\n{err}");
    assert!(out.contains("re-register the tracker"), "{out}");
    let text = std::fs::read_to_string(d.join("run/cell.json")).unwrap();
    let f: serde_json::Value = serde_json::from_str(&text).unwrap();
    let g = |k: &str| f[k].as_f64().unwrap();
    // The averaged normal: the floor and the calibration's own expected
    // error add in quadrature.
    let both = g("floor_deg").hypot(g("expected_deg"));
    assert!(g("after_deg") <= 1.2 * both, "{text}");
    assert_eq!(f["outcome"], "applied", "{text}");
    let rec: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run/record.json")).unwrap()).unwrap();
    let tilt = &rec["frames"]["errors"][0];
    assert_eq!(tilt["name"], "tracker tilt x");
    let deg = (tilt["value"].as_f64().unwrap() * 1e-6).to_degrees();
    assert!((deg - 0.05).abs() < 0.005, "{tilt}");
    assert_eq!(tilt["resolved"], true);
}

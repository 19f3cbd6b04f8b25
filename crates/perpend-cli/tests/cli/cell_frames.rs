//! `perpend cell run --reversal` end to end on the virtual board (issue 36
//! item 5): the board's world tilts the tracker by 0.05° about x
//! (`--tracker-tilt-deg 0.05`), the plan turns every pose to
//! 0/90/180/270° about the spindle axis; the run estimates the tilt within
//! 0.005°, its after error against the true planes is within 1.2× the
//! floor, and the record carries the estimate. Issue 46 item 4: at 10 µm
//! reading noise with one sample a pose (64 poses at the paper's
//! orientation, 1σ of the tilt ≈ 100 µrad, above the tolerance) the tilt
//! is still reported with its value and a warning, in frames.json and in
//! the record. Bounded in time; the board is killed at the end, also on
//! failure.
#![allow(clippy::unwrap_used, clippy::panic)]

use crate::common;

use std::process::{Command, Stdio};

use common::{board, Killed, BIN};

/// The paper's head and a plan of `n` poses within ±`tilt_max`° about
/// `center` (x,y in degrees), each at 0/90/180/270° about the spindle.
fn reversal_plan(d: &std::path::Path, n: &str, tilt_max: &str, center: &str) {
    common::ok(&["cell", "sim-head", "--out", "."], d);
    common::ok(
        &[
            "plan",
            "--sensors",
            "nominal.csv",
            "--n",
            n,
            "--tilt-max",
            tilt_max,
            "--center-tilt",
            center,
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

/// `perpend cell run --reversal` against a board whose tracker is tilted
/// by 0.05° about x, `samples` board samples a pose, `extra` options; its
/// standard output and the run directory.
fn tilted_run(d: &std::path::Path, samples: &str, extra: &[&str]) -> (String, std::path::PathBuf) {
    let (_board, bus, world) = board(d, "truth.csv", &["--tracker-tilt-deg", "0.05,0"]);
    let run = Killed(
        Command::new(BIN)
            .args(["--quiet", "cell", "run", "--node-id", "16", "--reversal"])
            .args(["--bus", &format!("tcp:{bus}")])
            .args(["--robot", &format!("sim:{world}")])
            .args(["--sensors", "nominal.csv", "--plan", "plan.csv"])
            .args(["--truth", "truth.csv", "--out", "run", "--samples", samples])
            .args(extra)
            .current_dir(d)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let (status, out, err) = common::finish(run, 300);
    assert!(status.success(), "{out}\n{err}");
    (out, d.join("run"))
}

fn json(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

#[test]
fn reversal_finds_a_tilted_tracker_and_the_head_reaches_the_floor() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    reversal_plan(d, "12", "8", "0,0");
    let (out, run) = tilted_run(d, "20", &[]);
    assert!(out.contains("re-register the tracker"), "{out}");
    let f = json(&run.join("cell.json"));
    let g = |k: &str| f[k].as_f64().unwrap();
    // The averaged normal: the floor and the calibration's own expected
    // error add in quadrature.
    let both = g("floor_deg").hypot(g("expected_deg"));
    assert!(g("after_deg") <= 1.2 * both, "{f}");
    assert_eq!(f["outcome"], "applied", "{f}");
    let rec = json(&run.join("record.json"));
    let tilt = &rec["frames"]["errors"][0];
    assert_eq!(tilt["name"], "tracker tilt x");
    let deg = (tilt["value"].as_f64().unwrap() * 1e-6).to_degrees();
    assert!((deg - 0.05).abs() < 0.005, "{tilt}");
    assert_eq!(tilt["resolved"], true);
}

/// The case: one 10 µm sample a pose, 64 poses at the paper's
/// orientation (17.89°, -1.04°) ± 5°. The tilt's 1σ (≈ 100 µrad) is above
/// half the calibration's expected error, so it is not resolved, but it is
/// estimated (truth within 4σ: a miss once in 16,000 runs if the 1σ is
/// right), significant, warned with the fix, and recorded with its value.
#[test]
fn a_tilt_at_ten_microns_a_reading_is_reported_with_a_value_and_warned() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    reversal_plan(d, "16", "5", "17.89,-1.04");
    // The frames are the point here, not the cell's decision on one sample
    // a pose: keep the new calibration whatever the decision says.
    let (out, run) = tilted_run(d, "1", &["--keep-worse"]);
    assert!(
        out.contains("tracker tilt x") && out.contains("re-register the tracker"),
        "{out}"
    );
    let frames = json(&run.join("frames.json"));
    let rec = json(&run.join("record.json"));
    assert_eq!(rec["frames"], frames);
    let tilt = &frames["errors"][0];
    let (v, s) = (
        tilt["value"].as_f64().unwrap(),
        tilt["sigma"].as_f64().unwrap(),
    );
    let truth = 0.05f64.to_radians() * 1e6;
    assert!((v - truth).abs() <= 4.0 * s, "{tilt}");
    assert_eq!(tilt["significant"], true, "{tilt}");
    let warned = frames["warnings"].as_array().unwrap().iter().any(|w| {
        let w = w.as_str().unwrap();
        w.starts_with("tracker tilt x") && w.contains("re-register the tracker")
    });
    assert!(warned, "{frames}");
    // the other tilt is reported too, with its value
    assert!(frames["errors"][1]["value"].is_f64(), "{frames}");
}

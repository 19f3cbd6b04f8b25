//! `perpend cell run` fails safe, against the virtual board: the bus
//! dropped during the push (`--fault bus:drop:0x2103:N`), the board reset
//! during the capture (`--fault bus:reset:0x2004:N`), bad, empty and ended
//! manual entries, and an after pass worse than the before pass. After
//! each, the board holds its previous calibration (pulled and compared with
//! `previous.json`), its residual limit and NMT state are as found and
//! calibration writes are locked; cell.json says what happened. Few poses
//! and samples: a few seconds each.
#![allow(clippy::unwrap_used, clippy::panic)]

use crate::common;

use std::io::{BufRead, BufReader, Write as _};
use std::net::TcpStream;
use std::path::Path;
use std::process::Stdio;

use common::{as_found, board, board_state, calibration, cell_json, cell_run, finish};

/// The run failed with `cause` first and left the board with its previous
/// calibration, as found otherwise.
fn failed_safely(d: &Path, bus: &str, out: &str, cause: &str, nmt: &str, err: &str) {
    let f = cell_json(d, out);
    assert_eq!(f["outcome"], "failed, restored", "{f}");
    let first = f["first_cause"].as_str().unwrap();
    assert!(first.contains(cause), "{first}");
    assert!(err.contains(&format!("error: {first}")), "{err}");
    assert_eq!(f["restore_problems"], serde_json::json!([]), "{f}");
    let state = board_state(d, bus, out);
    assert_eq!(
        state.sensors,
        calibration(d, &format!("{out}/previous.json"))
    );
    as_found(&state, nmt);
}

#[test]
fn the_bus_dropped_during_the_push_leaves_the_previous_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::head_and_plan(d, 8);
    // 0x2103: 23 reads by the pull, 23 by the push before it writes, then
    // the fifth write of sensor 3 is the one whose answer is lost.
    let (_board, bus, world) = board(d, "truth.csv", &["--fault", "bus:drop:0x2103:51"]);
    let robot = format!("sim:{world}");
    let run = cell_run(d, &bus, "run", &["--robot", &robot], Stdio::null());
    let (status, out, err) = finish(run, 120);
    assert!(!status.success(), "{out}");
    let cause = "pushing the new calibration: writing sensor 3";
    failed_safely(d, &bus, "run", cause, "pre-operational", &err);
    let f = cell_json(d, "run");
    let restored = f["restored"].to_string();
    assert!(restored.contains("previous calibration"), "{f}");
    assert!(f["before_deg"].as_f64().unwrap() > 0.5, "{f}");
    no_certificate(d, "run", "failed, restored");
    // The before pass was measured: the record and `record show` keep it.
    let rec: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run/record.json")).unwrap()).unwrap();
    assert_eq!(
        rec["verification"]["before_mean_deg"], f["before_deg"],
        "{rec}"
    );
}

/// A run whose calibration is not on the board leaves a record that says
/// so first, a report marked as no certificate with no PASS in it, and no
/// certificate; `record cert` refuses the record.
fn no_certificate(d: &Path, out: &str, outcome: &str) {
    let rec: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(d.join(format!("{out}/record.json"))).unwrap(),
    )
    .unwrap();
    assert_eq!(rec["outcome"], outcome, "{rec}");
    assert!(rec.get("stamp").is_none(), "{rec}");
    assert!(!d.join(format!("{out}/cert.html")).exists());
    let report = std::fs::read_to_string(d.join(format!("{out}/report.html"))).unwrap();
    assert!(report.contains("NOT A CERTIFICATE"), "{report}");
    assert!(report.contains(&format!("Outcome: {outcome}")));
    assert!(!report.contains("PASS"), "{report}");
    let shown = common::ok(&["record", "show", &format!("{out}/record.json")], d);
    assert!(
        shown.starts_with(&format!("outcome: {outcome}\n")),
        "{shown}"
    );
    assert!(!shown.contains("PASS"), "{shown}");
    let cert = std::process::Command::new(common::BIN)
        .args([
            "record",
            "cert",
            &format!("{out}/record.json"),
            "--out",
            "c.html",
        ])
        .current_dir(d)
        .output()
        .unwrap();
    assert!(!cert.status.success());
    let e = String::from_utf8_lossy(&cert.stderr);
    assert!(e.contains("no certificate for this record"), "{e}");
    assert!(!d.join("c.html").exists());
}

#[test]
fn a_board_reset_during_the_capture_stops_the_run_safely() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::head_and_plan(d, 8);
    let (_board, bus, world) = board(d, "truth.csv", &["--fault", "bus:reset:0x2004:40"]);
    let robot = format!("sim:{world}");
    let run = cell_run(d, &bus, "run", &["--robot", &robot], Stdio::null());
    let (status, out, err) = finish(run, 120);
    assert!(!status.success(), "{out}");
    let cause = "reset itself during the capture of pose";
    failed_safely(d, &bus, "run", cause, "pre-operational", &err);
    assert!(err.contains("nothing was pushed"), "{err}");
}

#[test]
fn manual_entries_are_asked_again_and_the_end_of_input_stops_safely() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::head_and_plan(d, 8);
    let (_board, bus, _world) = board(d, "truth.csv", &[]);
    let mut run = cell_run(d, &bus, "run", &["--robot", "manual"], Stdio::piped());
    // The two verification poses: a word, an empty line, the planned plane
    // in inches, the planned plane as printed, then a measured plane; no
    // plane, `1,2,3,4`, a plane 3 mm off the plan's standoff, then a
    // measured plane; then the end.
    let out = answer_prompts(
        &mut run,
        &[
            &["hello", "", "INCH", "COPY"],
            &["0,0,0,5", "1,2,3,4", "FAR"],
        ],
    );
    let (status, _, err) = finish(run, 120);
    assert!(!status.success(), "{out}");
    for why in [
        "'hello' refused: not four numbers A,B,C,D",
        "'' refused: not four numbers A,B,C,D",
        "refused: a plane in inches: D = ",
        "'0,0,0,5' refused: not a plane: |(A,B,C)| = 0",
        "'1,2,3,4' refused: ",
        "refused: the planned plane as printed, not a measurement",
        "mm, the plan's is",
        "before calibration, normal error",
    ] {
        assert!(out.contains(why), "{why}: {out}\n{err}");
    }
    let cause = "reading the tracker's plane: end of input at pose 1 (nothing was captured)";
    failed_safely(d, &bus, "run", cause, "pre-operational", &err);
}

#[test]
fn the_end_of_input_at_the_first_prompt_puts_back_limit_and_nmt_state() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::head_and_plan(d, 8);
    let (_board, bus, _world) = board(d, "truth.csv", &[]);
    let link = format!("tcp:{bus}");
    common::ok(
        &["node", "--bus", &link, "--node-id", "16", "nmt", "start"],
        d,
    );
    let run = cell_run(d, &bus, "run", &["--robot", "manual"], Stdio::null());
    let (status, out, err) = finish(run, 60);
    assert!(!status.success(), "{out}");
    let cause = "end of input at before: verification pose 1";
    failed_safely(d, &bus, "run", cause, "operational", &err);
    let f = cell_json(d, "run");
    assert!(
        f["restored"].to_string().contains("0x2300 sub 4 back"),
        "{f}"
    );
}

/// The planned plane a manual prompt prints (`None`: not a prompt).
fn planned_plane(line: &str) -> Option<&str> {
    line.split("(planned plane ")
        .nth(1)
        .and_then(|t| t.split(')').next())
}

/// Answers the first manual prompts of `run`: for prompt k the lines of
/// `bad[k]` (`INCH`: the planned plane with D in inches, `FAR`: 3 mm
/// beyond its standoff, `COPY`: the planned plane as printed), then the
/// planned plane as a tracker measures it (20 µm further); then closes
/// the input.
/// Returns what the run printed until then.
fn answer_prompts(run: &mut common::Killed, bad: &[&[&str]]) -> String {
    let mut stdin = run.0.stdin.take().unwrap();
    let stdout = BufReader::new(run.0.stdout.take().unwrap());
    let mut seen = String::new();
    let mut k = 0;
    let mut lines = stdout.lines();
    while let Some(Ok(line)) = lines.next() {
        seen.push_str(&line);
        seen.push('\n');
        let Some(plane) = planned_plane(&line) else {
            continue;
        };
        let Some(answers) = bad.get(k) else {
            break;
        };
        k += 1;
        let v: Vec<f64> = plane.split(',').map(|x| x.parse().unwrap()).collect();
        let with_d = |dd: f64| format!("{},{},{},{dd}", v[0], v[1], v[2]);
        for a in answers.iter() {
            let a = match *a {
                "INCH" => with_d(v[3] / 25.4),
                "FAR" => with_d(v[3] - 3.0 * v[2]),
                "COPY" => plane.to_string(),
                a => a.to_string(),
            };
            stdin.write_all(format!("{a}\n").as_bytes()).unwrap();
        }
        let measured = with_d(v[3] - 0.02 * v[2]);
        stdin.write_all(format!("{measured}\n").as_bytes()).unwrap();
    }
    drop(stdin);
    // Keep reading: the run reports on standard output.
    std::thread::spawn(move || lines.for_each(drop));
    seen
}

/// Answers the manual prompts of `run` through the world channel: the
/// plane of each prompt goes to the board, the tracker reads it exactly at
/// the verification poses and tilted ±0.5° at the captured ones (a tracker
/// that lies while the calibration is captured).
fn lying_tracker(run: &mut common::Killed, world: &str) {
    let mut w = BufReader::new(TcpStream::connect(world).unwrap());
    let mut stdin = run.0.stdin.take().unwrap();
    let stdout = BufReader::new(run.0.stdout.take().unwrap());
    for (k, line) in stdout.lines().map_while(Result::ok).enumerate() {
        let Some(plane) = planned_plane(&line) else {
            continue;
        };
        w.get_mut()
            .write_all(format!("plane {plane}\n").as_bytes())
            .unwrap();
        let mut ok = String::new();
        w.read_line(&mut ok).unwrap();
        assert_eq!(ok.trim(), "ok");
        let mut v: Vec<f64> = plane.split(',').map(|x| x.parse().unwrap()).collect();
        if line.starts_with("pose ") {
            v[0] += if k % 2 == 0 { 0.009 } else { -0.009 };
        }
        // A measurement, not the plan as printed: 20 µm further.
        v[3] -= 0.02 * v[2];
        let typed = format!("{},{},{},{}\n", v[0], v[1], v[2], v[3]);
        if stdin.write_all(typed.as_bytes()).is_err() {
            break;
        }
    }
}

#[test]
fn an_after_pass_worse_than_the_before_pass_reverts_the_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::head_and_plan(d, 8);
    // The board is built as it is stored: already perfect before.
    let (_board, bus, world) = board(d, "nominal.csv", &[]);
    let mut run = cell_run(d, &bus, "run", &["--robot", "manual"], Stdio::piped());
    lying_tracker(&mut run, &world);
    let (status, out, err) = finish(run, 120);
    assert!(!status.success(), "{out}");
    let f = cell_json(d, "run");
    assert_eq!(f["outcome"], "reverted", "{f}");
    let (before, after) = (
        f["before_deg"].as_f64().unwrap(),
        f["after_deg"].as_f64().unwrap(),
    );
    assert!(after > before, "{f}");
    let first = f["first_cause"].as_str().unwrap();
    assert!(
        first.contains("is worse than before") || first.starts_with("FAIL: at pose"),
        "{f}"
    );
    assert!(err.contains(&format!("error: {first}")), "{err}");
    let state = board_state(d, &bus, "run");
    assert_eq!(state.sensors, calibration(d, "run/previous.json"));
    as_found(&state, "pre-operational");
    // The record says what happened, and the board's pulled calibration
    // carries the stamp it had before the run (pushed back with it).
    let rec: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run/record.json")).unwrap()).unwrap();
    let events = rec["events"].to_string();
    assert!(events.contains("perpend cell run: reverted"), "{events}");
    no_certificate(d, "run", "reverted");
    let prev: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run/previous.json")).unwrap())
            .unwrap();
    let now: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run/now.json")).unwrap()).unwrap();
    // (A board never stamped pulls without `calibration_stamp`: hash 0.)
    let hash = |v: &serde_json::Value| {
        let st = &v["calibration_stamp"];
        let h = st["record_hash"].as_str().unwrap_or("00000000").to_string();
        (h, st["utc_s"].as_u64().unwrap_or(0))
    };
    assert_eq!(hash(&now), hash(&prev), "{now}");
}

#[test]
fn keep_worse_keeps_the_new_calibration_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::head_and_plan(d, 8);
    let (_board, bus, world) = board(d, "nominal.csv", &[]);
    let extra = ["--robot", "manual", "--keep-worse"];
    let mut run = cell_run(d, &bus, "run", &extra, Stdio::piped());
    lying_tracker(&mut run, &world);
    // Standard output went to the lying tracker.
    let (status, _, err) = finish(run, 120);
    assert!(status.success(), "{err}");
    let f = cell_json(d, "run");
    assert_eq!(f["outcome"], "applied", "{f}");
    assert!(
        f["reason"].as_str().unwrap().contains("--keep-worse"),
        "{f}"
    );
    let state = board_state(d, &bus, "run");
    let new = calibration(d, "run/params.json");
    assert!(common::same_geometry(&state.sensors, &new), "{state:?}");
    as_found(&state, "pre-operational");
}

#[test]
fn ctrl_c_at_a_manual_prompt_puts_back_what_the_run_changed() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    common::head_and_plan(d, 8);
    let (_board, bus, _world) = board(d, "truth.csv", &[]);
    let mut run = cell_run(d, &bus, "run", &["--robot", "manual"], Stdio::piped());
    // The operator types nothing; the residual limit is raised by now.
    let _stdin = run.0.stdin.take().unwrap();
    let mut lines = BufReader::new(run.0.stdout.take().unwrap()).lines();
    for line in lines.by_ref().map_while(Result::ok) {
        if planned_plane(&line).is_some() {
            break;
        }
    }
    // Keep reading: the run reports on standard output.
    std::thread::spawn(move || lines.for_each(drop));
    let pid = run.0.id().to_string();
    let kill = std::process::Command::new("kill")
        .args(["-INT", &pid])
        .status()
        .unwrap();
    assert!(kill.success());
    let (status, _, err) = finish(run, 60);
    assert!(!status.success(), "{err}");
    let cause = "interrupted (Ctrl-C) during before: verification pose 1";
    failed_safely(d, &bus, "run", cause, "pre-operational", &err);
    let f = cell_json(d, "run");
    assert!(
        f["restored"].to_string().contains("0x2300 sub 4 back"),
        "{f}"
    );
}

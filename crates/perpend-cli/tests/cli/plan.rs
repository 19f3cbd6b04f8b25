//! `perpend plan` and `perpend bench plan` as a user runs them (issue 12,
//! item 3): the plan file, its JSON, the bench's keys and its goal.
#![allow(clippy::unwrap_used)]

use std::process::Command;

fn perpend(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn plan_writes_the_poses_and_their_expected_accuracy() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().to_str().unwrap();
    let out = perpend(&["simulate", "--out", d, "--seed", "3"]);
    assert!(out.status.success());
    let csv = dir.path().join("plan.csv");
    let s = dir.path().join("sensors.csv");
    let out = perpend(&[
        "plan",
        "--sensors",
        s.to_str().unwrap(),
        "--n",
        "14",
        "--center-tilt",
        "17.9,-1.0",
        "--tilt-max",
        "5",
        "--standoff",
        "26.5,29.5",
        "--draws",
        "8",
        "--out",
        csv.to_str().unwrap(),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["poses"].as_array().unwrap().len(), 14);
    let e = &v["expected"];
    assert_eq!(e["ok"], 8);
    let (l, f) = (
        e["lsq_mean_deg"].as_f64().unwrap(),
        e["floor_mean_deg"].as_f64().unwrap(),
    );
    assert!(l >= f * 0.9 && l < 1.3 * f, "lsq {l} floor {f}");
    let text = std::fs::read_to_string(&csv).unwrap();
    assert_eq!(text.lines().filter(|x| !x.starts_with('#')).count(), 15);
    assert!(text.contains("pose,tilt_x_deg,tilt_y_deg,standoff_mm,a,b,c,d_mm"));

    // A reach that cannot hold the poses asked for is a sentence.
    let out = perpend(&[
        "plan",
        "--sensors",
        s.to_str().unwrap(),
        "--n",
        "500",
        "--standoff",
        "26,30",
        "--out",
        csv.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("reachable"));
}

#[test]
fn bench_plan_meets_its_goal_with_at_most_twenty_poses() {
    let out = perpend(&["bench", "plan", "--seeds", "40", "--json"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in ["planned", "random"] {
        let rows = v[key].as_array().unwrap();
        let n: Vec<u64> = rows.iter().map(|r| r["poses"].as_u64().unwrap()).collect();
        assert_eq!(n, [8, 12, 16, 20, 30, 50, 100]);
        for r in rows {
            assert!(r["lsq_mean_deg"].as_f64().unwrap() > 0.0);
            assert!(r["floor_mean_deg"].as_f64().unwrap() > 0.0);
        }
    }
    let goal = v["planned_poses_to_goal"].as_u64();
    assert!(goal.is_some_and(|g| g <= 20), "{goal:?}");
}

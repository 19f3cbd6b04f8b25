//! The conventions and the file columns are where a user looks: in
//! `perpend --help` and in the help of the commands that read files.
#![allow(clippy::unwrap_used)]

use std::process::Command;

fn help(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(args)
        .output()
        .unwrap();
    assert!(out.status.success(), "{args:?}");
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn top_level_help_states_the_conventions() {
    let h = help(&["--help"]);
    for needle in [
        "+z along the spindle feed",
        "towards the head",
        "θ1",
        "Pitch",
        "Chen eq. 22",
    ] {
        assert!(
            h.contains(needle),
            "`perpend --help` lacks {needle:?}:\n{h}"
        );
    }
}

#[test]
fn commands_that_read_files_name_their_columns() {
    for cmd in ["calibrate", "diagnose", "measure"] {
        let h = help(&[cmd, "--help"]);
        for needle in [
            "sensors.csv",
            "x_mm",
            "d_mm",
            "d1_mm",
            "sigma_mm",
            "temp_c",
            "docs/data-format.md",
        ] {
            assert!(
                h.contains(needle),
                "`perpend {cmd} --help` lacks {needle:?}:\n{h}"
            );
        }
    }
}

#[test]
fn errors_with_json_are_json_and_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let sensors = dir.path().join("sensors.csv");
    std::fs::write(
        &sensors,
        "sensor;x_mm;y_mm;z_mm;m;n;q\n1;0,0;45;0;0;0,4;1\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(["diagnose", "--json", "--sensors"])
        .arg(&sensors)
        .arg("--poses")
        .arg(dir.path().join("poses.csv"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["file"].as_str().unwrap().ends_with("sensors.csv"), "{v}");
    assert_eq!(v["line"], 1, "{v}");
    let msg = v["error"].as_str().unwrap();
    assert!(msg.contains("separated by `;`"), "{msg}");
}

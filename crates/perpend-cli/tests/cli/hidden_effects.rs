//! Hidden-effect tests of `perpend diagnose` (issue 5, item 3; issue 10,
//! item 8).
//!
//! The test of record, [`bench_diagnose_scores_the_independent_generator`],
//! takes its runs from `host-tests/blind/gen.py`, which shares no code with
//! perpend (other head geometries, plane sampling, tracker, noise and
//! effect shapes than the candidates' terms), through `perpend bench
//! diagnose` (CI's blind step runs the reduced grid the same way). The
//! others use perpend's own simulator, whose effects are injected through
//! the candidates' own terms: they check the pipeline's consistency with
//! itself (verdicts, JSON keys, skipped candidates), not that it recognises
//! effects it was not built around.
//!
//! A seed picks the hidden effect — none, one of the catalogue, or the
//! out-of-catalogue ripple (a periodic linearity error) — and its size and
//! noise ([`Scenario::draw`]); the simulator generates the run; only the
//! exchange-format files are written to a temporary directory; the built
//! `perpend` binary diagnoses them exactly as a user would
//! (`perpend diagnose --sensors … --poses … --json`); only then is the
//! answer compared with the hidden truth. The truth never reaches the tool.
#![allow(clippy::unwrap_used)]

use std::path::Path;
use std::process::Command;

use perpend_diagnosis::diagnose::scenario::{generate, write, Hidden, Scenario};
use perpend_diagnosis::diagnose::DiagnoseJson;

fn perpend(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(args)
        .output()
        .unwrap()
}

fn diagnose_json(dir: &Path) -> (DiagnoseJson, serde_json::Value) {
    let s = dir.join("sensors.csv");
    let p = dir.join("poses.csv");
    let out = perpend(&[
        "diagnose",
        "--sensors",
        s.to_str().unwrap(),
        "--poses",
        p.to_str().unwrap(),
        "--json",
    ]);
    assert!(
        out.status.success(),
        "diagnose failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8(out.stdout).unwrap();
    let v: serde_json::Value = serde_json::from_str(text.trim()).unwrap();
    assert!(
        text.starts_with("{\"schema\":\"perpend.diagnose/1\","),
        "{text}"
    );
    // `DiagnoseJson` denies unknown fields: beside its schema tag, the
    // object has exactly the keys.
    let mut body = v.clone();
    if let Some(m) = body.as_object_mut() {
        m.remove("schema");
    }
    let d: DiagnoseJson = serde_json::from_value(body).unwrap();
    (d, v)
}

/// `perpend bench diagnose` on a handful of the independent generator's
/// base-regime runs (tuning seeds): effect-free runs, a single effect,
/// a pair and tracker blunders, each diagnosed by this binary from its two
/// files and graded by `score.py` against the hidden truth; the grid comes
/// back as JSON on standard output, and a missed goal fails `--check`.
#[test]
fn bench_diagnose_scores_the_independent_generator() {
    let out = perpend(&[
        "bench",
        "diagnose",
        "--regime",
        "base",
        "--nulls",
        "2",
        "--effects",
        "1",
        "--only",
        "none,gain,gain+thermal_lag,blunders",
        "--jobs",
        "2",
        "--json",
        "--check",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let base = &v["base"];
    assert_eq!(base["none"]["n"], 2, "{v}");
    assert_eq!(base["none"]["false_positive_rate"], 0.0, "{v}");
    assert_eq!(base["blunders"]["found_rate"], 1.0, "{v}");
    // The effects are graded where visible at >= 1x the noise; each class
    // present must be named and brought back to the same-draw floor.
    let mut graded = 0;
    for cls in ["single", "pair"] {
        if let Some(k) = base.get(cls) {
            graded += k["n"].as_u64().unwrap();
            assert_eq!(k["rate"], 1.0, "{cls}: {v}");
            // over the least cost of estimating the named model's extras
            // (score.py `estimation_cost`)
            assert!(k["adj_max"].as_f64().unwrap() <= 1.15, "{cls}: {v}");
            assert!(
                k["adj_max"].as_f64() <= k["same_max"].as_f64(),
                "{cls}: {v}"
            );
        }
    }
    assert!(graded >= 1, "nothing graded: {v}");
    assert!(err.contains("| base |"), "the table goes to stderr: {err}");
}

/// The carry-over test of a named incidence (`select.rs`, "Carry-over")
/// on the independent generator's quadratic carry-over (`crosstalk_sq`,
/// off both catalogues: it grows with the square of the step from the
/// channel converted before), the 8 base-regime runs of the off-catalogue
/// block's tuning range (seed base 1400000). Without the test the spot
/// form took it for incidence alone in 6 of the 8; with it in 3 (where it
/// follows the carry-over to within the noise, which nothing in the
/// residuals separates), and `unexplained` with incidence the partial
/// winner in 3.
#[test]
fn a_carry_over_in_the_spot_form_s_shape_is_not_taken_for_incidence() {
    let dir = tempfile::tempdir().unwrap();
    let runs = dir.path().join("runs.jsonl");
    let out = perpend(&[
        "bench",
        "diagnose",
        "--offcat",
        "--seed-base",
        "1400000",
        "--nulls",
        "1",
        "--effects",
        "8",
        "--regime",
        "base",
        "--only",
        "crosstalk_sq",
        "--jobs",
        "2",
        "--quiet",
        "--runs",
        runs.to_str().unwrap(),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    let text = std::fs::read_to_string(&runs).unwrap_or_else(|e| panic!("{e}: {err}"));
    let said: Vec<(String, Vec<String>)> = text
        .lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            let a = &v["answer"];
            let named = a["effects"].as_array().map_or(Vec::new(), |e| {
                e.iter()
                    .map(|x| x["effect"].as_str().unwrap_or("").to_string())
                    .collect()
            });
            (a["effect"].as_str().unwrap_or("").to_string(), named)
        })
        .collect();
    assert_eq!(said.len(), 8, "{err}");
    let incidence_alone = said
        .iter()
        .filter(|(e, n)| e == "incidence" && n.len() == 1)
        .count();
    let caught = said
        .iter()
        .filter(|(e, n)| e == "unexplained" && n.iter().any(|x| x == "incidence"))
        .count();
    assert!(incidence_alone <= 3, "{said:?}");
    assert!(caught >= 3, "{said:?}");
}

/// Self-consistency on perpend's own simulator. Seeds 0..16: every kind
/// twice (the seed picks `Hidden::ALL[seed mod 8]`).
#[test]
fn hidden_effects_are_named_from_the_files_alone() {
    let mut wrong = Vec::new();
    for seed in 0..16u64 {
        let sc = Scenario::draw(seed, &Hidden::ALL, 100);
        let g = generate(&sc).unwrap();
        let dir = tempfile::tempdir().unwrap();
        write(&g.data, dir.path()).unwrap();
        // Nothing but the two exchange files goes to the tool.
        let mut names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names, ["poses.csv", "sensors.csv"]);
        let (d, v) = diagnose_json(dir.path());

        // Only now: the hidden truth.
        let want = sc.hidden.correct_verdict();
        if d.effect != want {
            // The report's verdict section says why, for whoever reads the failure.
            let s = dir.path().join("sensors.csv");
            let p = dir.path().join("poses.csv");
            let out = perpend(&[
                "diagnose",
                "--sensors",
                s.to_str().unwrap(),
                "--poses",
                p.to_str().unwrap(),
            ]);
            let text = String::from_utf8_lossy(&out.stdout).into_owned();
            let verdict = text
                .split("\nVerdict")
                .nth(1)
                .unwrap_or("")
                .lines()
                .take(6)
                .collect::<Vec<_>>()
                .join("\n    ");
            wrong.push(format!(
                "seed {seed}: hidden {} (magnitude {:.2} σ, σ = {:.4} mm) named {}\n    {verdict}",
                sc.hidden.name(),
                sc.magnitude,
                sc.sigma_mm,
                d.effect
            ));
            continue;
        }
        let keys: Vec<&str> = v.as_object().unwrap().keys().map(String::as_str).collect();
        // The eleven and `schema`, and a `none`'s detection limits.
        let limits = usize::from(d.effect == "none");
        assert_eq!(keys.len(), 12 + limits, "{keys:?}");
        assert_eq!(keys.contains(&"detection_limits"), limits == 1, "{keys:?}");
        assert!(d.folds >= 5, "seed {seed}: {} folds", d.folds);
        assert!(
            d.outlier_poses.is_empty(),
            "seed {seed}: {:?}",
            d.outlier_poses
        );
        match d.effect.as_str() {
            "none" => assert!(d.effects.is_empty(), "seed {seed}"),
            "unexplained" => {}
            e => assert_eq!(d.effects[0].effect, e, "seed {seed}"),
        }
        assert!(d.expected_rms_mm > 0.0);
        assert!(d.candidates.iter().any(|c| c.effect == "none"));
        if sc.hidden.in_catalog() {
            // The extension brings the held-out RMS back to the floor and
            // improves the normal.
            assert!(
                d.extended.heldout_rms_mm <= 1.15 * d.expected_rms_mm,
                "seed {seed}: extended {} vs floor {}",
                d.extended.heldout_rms_mm,
                d.expected_rms_mm
            );
            assert!(d.extended.heldout_rms_mm < d.base.heldout_rms_mm);
            assert!(
                d.extended.heldout_normal_err_deg.unwrap() < d.base.heldout_normal_err_deg.unwrap(),
                "seed {seed}: normal error not improved"
            );
        } else {
            assert_eq!(
                d.extended, d.base,
                "seed {seed}: none/unexplained repeat base"
            );
        }
    }
    assert!(wrong.is_empty(), "misnamed:\n{}", wrong.join("\n"));
}

#[test]
fn candidates_without_their_inputs_are_skipped() {
    // A drift run written without t_s and temp_c: drift and thermal cannot
    // be tested, and the tool must not invent them.
    let sc = Scenario {
        seed: 6,
        hidden: Hidden::Drift,
        magnitude: 3.0,
        poses: 100,
        sigma_mm: 0.01,
        with_time: false,
        with_temp: false,
    };
    let g = generate(&sc).unwrap();
    let dir = tempfile::tempdir().unwrap();
    write(&g.data, dir.path()).unwrap();
    let (d, _) = diagnose_json(dir.path());
    let names: Vec<&str> = d.candidates.iter().map(|c| c.effect.as_str()).collect();
    assert!(
        !names.contains(&"drift") && !names.contains(&"thermal"),
        "{names:?}"
    );
    assert!(names.contains(&"gain") && names.contains(&"crosstalk"));
    // A drift the catalogue cannot test is still seen: its residuals are
    // structured in acquisition order, and nothing removes that.
    assert_eq!(d.effect, "unexplained");

    let s = dir.path().join("sensors.csv");
    let p = dir.path().join("poses.csv");
    let out = perpend(&[
        "diagnose",
        "--sensors",
        s.to_str().unwrap(),
        "--poses",
        p.to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.contains("skipped: thermal (no temp_c column"),
        "{text}"
    );
    assert!(text.contains("skipped: drift (no t_s column"), "{text}");
    assert!(text.contains("What the simulation gets wrong"));
}

/// Without any declared noise the diagnosis estimates it from the run and
/// says so; with one, it reports both.
#[test]
fn declared_noise_is_optional_and_plots_are_svg() {
    let sc = Scenario::draw(9, &Hidden::ALL, 60); // gain
    assert_eq!(sc.hidden, Hidden::Gain);
    let mut g = generate(&sc).unwrap();
    for r in g.data.sensors.rows.iter_mut() {
        r.sigma_mm = None;
    }
    let dir = tempfile::tempdir().unwrap();
    write(&g.data, dir.path()).unwrap();
    let s = dir.path().join("sensors.csv");
    let p = dir.path().join("poses.csv");
    let (s, p) = (s.to_str().unwrap(), p.to_str().unwrap());
    let out = perpend(&["diagnose", "--sensors", s, "--poses", p]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("none declared"), "{text}");
    assert!(text.contains("Verdict: gain"), "{text}");

    let sigma = format!("{}", sc.sigma_mm);
    let plots = dir.path().join("plots");
    let out = perpend(&[
        "diagnose",
        "--sensors",
        s,
        "--poses",
        p,
        "--sigma-mm",
        &sigma,
        "--plot",
        plots.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("Verdict: gain"), "{text}");
    assert!(
        text.contains("declared") && text.contains("--sigma-mm"),
        "{text}"
    );
    for f in ["residuals.svg", "normal_errors.svg"] {
        let svg = std::fs::read_to_string(plots.join(f)).unwrap();
        assert!(svg.starts_with("<svg"), "{f}");
        assert!(svg.contains("held-out"), "{f}");
    }
}

#[test]
fn malformed_input_names_file_and_line() {
    let dir = tempfile::tempdir().unwrap();
    let s = dir.path().join("sensors.csv");
    let p = dir.path().join("poses.csv");
    std::fs::write(
        &s,
        "sensor,x_mm,y_mm,z_mm,m,n,q,sigma_mm\n1,50,0,0,-0.5,0,0.866,0.01\n2,0,50,0,0,-0.5,0.866,0.01\n3,-50,0,0,0.5,0,0.866,0.01\n4,0,-50,0,0,0.5,0.866,0.01\n",
    )
    .unwrap();
    std::fs::write(
        &p,
        "pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm\n1,0,0,1,-40,41,x,41,41\n",
    )
    .unwrap();
    let out = perpend(&[
        "diagnose",
        "--sensors",
        s.to_str().unwrap(),
        "--poses",
        p.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("poses.csv") && err.contains("line 2") && err.contains("d2_mm"),
        "{err}"
    );
}

//! Extension coefficients belong to the stored calibration (issue 5, item
//! 2): fitted per sensor with the diagnosis' candidate terms, written to
//! the parameter JSON, read back, and applied by `perpend-core` when it
//! turns readings into spots — and a head with them measures the normal of
//! held-out poses better than the paper's model.
#![allow(clippy::unwrap_used)]

use perpend_calib::candidates::{fit, line_angle_deg, Effect, Refs};
use perpend_core::calib::{LsqConfig, Poses};
use perpend_core::normal::{measure, Method};
use perpend_diagnosis::diagnose::scenario::{generate, Hidden, Scenario};
use perpend_formats::exchange::PoseTable;
use perpend_formats::paramfile::{ParamFile, SensorParams};

fn split(p: &PoseTable, at: usize) -> (PoseTable, PoseTable) {
    let a = PoseTable {
        n_sensors: p.n_sensors,
        rows: p.rows[..at].to_vec(),
    };
    let b = PoseTable {
        n_sensors: p.n_sensors,
        rows: p.rows[at..].to_vec(),
    };
    (a, b)
}

/// Mean normal error [deg] over `test` of the head stored in `file`,
/// against the true planes.
fn stored_head_error(
    file: &ParamFile,
    test: &PoseTable,
    truth: &[perpend_core::geometry::Plane<f64>],
) -> f64 {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("params.json");
    file.write(&path).unwrap();
    let head = ParamFile::read(&path).unwrap().to_head::<4>().unwrap();
    let mut sum = 0.0;
    for (k, plane) in truth.iter().enumerate().take(test.len()) {
        let r = &test.rows[k].readings;
        let r4 = [r[0], r[1], r[2], r[3]];
        let m = measure(&head, &r4, &test.context(k), Method::LeastSquares).unwrap();
        sum += line_angle_deg(&m.plane.normal, &plane.n);
    }
    sum / test.len() as f64
}

#[test]
fn stored_extensions_measure_held_out_normals_better() {
    let cases = [
        (Hidden::Gain, Effect::Gain),
        (Hidden::Nonlinearity, Effect::Nonlinearity),
        (Hidden::Incidence, Effect::Incidence),
        (Hidden::Crosstalk, Effect::Crosstalk),
        (Hidden::Thermal, Effect::Thermal),
        (Hidden::Drift, Effect::Drift),
    ];
    for (k, (hidden, effect)) in cases.into_iter().enumerate() {
        let sc = Scenario {
            seed: 40 + k as u64,
            hidden,
            magnitude: 3.0,
            poses: 120,
            sigma_mm: 0.008,
            with_time: true,
            with_temp: true,
        };
        let g = generate(&sc).unwrap();
        // Calibrate on the first 80 poses, measure the last 40.
        let (train, test) = split(&g.data.poses, 80);
        let truth = &g.data.true_planes[80..];
        let nominal = g.data.sensors.sensors().unwrap();
        let refs = Refs::of(&train);
        let cfg = LsqConfig::default();
        let mut base = ParamFile::new("lsq", "base", train.len());
        let mut ext = ParamFile::new("lsq", effect.name(), train.len());
        for (i, s) in nominal.iter().enumerate() {
            let b = fit(s, i, &train, refs.terms(Effect::None, i), &cfg).unwrap();
            let e = fit(s, i, &train, refs.terms(effect, i), &cfg).unwrap();
            base.sensors
                .push(SensorParams::from_sensor(i + 1, &b.sensor, Some(s)));
            let mut p = SensorParams::from_sensor(i + 1, &e.sensor, Some(s));
            p.sigma_ext = e.sigma.clone();
            ext.sensors.push(p);
        }
        // The JSON carries the coefficients.
        let json = serde_json::to_string(&ext).unwrap();
        let back = ParamFile::parse(&json, "mem").unwrap();
        assert_eq!(back, ext);
        assert!(back.sensors.iter().any(|s| s.ext != base.sensors[0].ext));

        let eb = stored_head_error(&base, &test, truth);
        let ee = stored_head_error(&ext, &test, truth);
        // The true head with the true extension, through the same stored
        // path: what perfect calibration of the extended model achieves on
        // the same readings. (For incidence this is limited by the core's
        // two-pass γ in `normal::plane`: 0.040° here against 0.012° with γ
        // iterated to convergence; see the diagnosis report.)
        let mut tf = ParamFile::new("truth", effect.name(), 0);
        for (i, s) in g.head.truth.iter().enumerate() {
            let mut s = *s;
            s.ext = g.ext[i];
            tf.sensors.push(SensorParams::from_sensor(i + 1, &s, None));
        }
        let floor = if hidden == Hidden::Crosstalk {
            // Injected by the ADC model, not as an Extension: no stored truth.
            None
        } else {
            Some(stored_head_error(&tf, &test, truth))
        };
        assert!(
            ee < eb,
            "{}: extended {ee:.4}° vs base {eb:.4}° (floor {floor:?})",
            effect.name()
        );
        if let Some(f) = floor {
            assert!(
                ee < 1.3 * f,
                "{}: extended {ee:.4}° vs floor {f:.4}°",
                effect.name()
            );
        }
    }
}

/// As a user would: `perpend diagnose --out` on the calibration files
/// stores the named extension; `perpend calibrate --out` stores the
/// paper's model; the stored extended head measures held-out normals
/// better.
#[test]
fn diagnose_out_stores_the_named_extension() {
    let sc = Scenario {
        seed: 77,
        hidden: Hidden::Gain,
        magnitude: 3.0,
        poses: 120,
        sigma_mm: 0.008,
        with_time: true,
        with_temp: true,
    };
    let g = generate(&sc).unwrap();
    let (train, test) = split(&g.data.poses, 80);
    let dir = tempfile::tempdir().unwrap();
    perpend_formats::exchange::write_dataset(dir.path(), &g.data.sensors, &train, &[]).unwrap();
    let s = dir.path().join("sensors.csv");
    let p = dir.path().join("poses.csv");
    let ext_json = dir.path().join("ext.json");
    let base_json = dir.path().join("base.json");
    let run = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_perpend"))
            .args(args)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).unwrap()
    };
    let (s, p) = (s.to_str().unwrap(), p.to_str().unwrap());
    let text = run(&[
        "diagnose",
        "--sensors",
        s,
        "--poses",
        p,
        "--out",
        ext_json.to_str().unwrap(),
    ]);
    assert!(text.contains("Verdict: gain"), "{text}");
    run(&[
        "calibrate",
        "--sensors",
        s,
        "--poses",
        p,
        "--out",
        base_json.to_str().unwrap(),
    ]);
    let ext = ParamFile::read(&ext_json).unwrap();
    assert_eq!(ext.model, "gain");
    assert!(ext
        .sensors
        .iter()
        .all(|x| x.ext.gain != 0.0 && x.sigma_ext.len() == 1));
    let base = ParamFile::read(&base_json).unwrap();
    let truth = &g.data.true_planes[80..];
    let eb = stored_head_error(&base, &test, truth);
    let ee = stored_head_error(&ext, &test, truth);
    assert!(ee < 0.6 * eb, "extended {ee:.4}° vs base {eb:.4}°");
}

/// A linearity error no polynomial candidate has (one sine period over
/// each sensor's range, added to the simulated readings, not injected
/// through the core's terms): `perpend calibrate --model linearity_table`
/// stores a table per sensor, the file reads back to the same tables, and
/// the stored head (the board's inversion of the reading model) measures
/// held-out normals far better than the paper's model and as well as the
/// cubic (whose misfit, inside the run, costs the normal little).
#[test]
fn calibrate_stores_a_linearity_table_that_measures_better() {
    use perpend_calib::sim::{paper_head, simulate, SimConfig};
    use rand::SeedableRng;
    let head = paper_head().unwrap();
    let mut cfg = SimConfig::paper();
    cfg.poses = 150;
    let mut rng = rand::rngs::StdRng::seed_from_u64(21);
    let mut data = simulate(&head, &cfg, &[], &mut rng).unwrap();
    perpend_calib::sim::add_sine_linearity(&mut data.poses, &[0.06, -0.05, 0.055, -0.06]);
    let (train, test) = split(&data.poses, 100);
    let dir = tempfile::tempdir().unwrap();
    perpend_formats::exchange::write_dataset(dir.path(), &data.sensors, &train, &[]).unwrap();
    let (s, p) = (dir.path().join("sensors.csv"), dir.path().join("poses.csv"));
    let calibrate = |model: &str| {
        let out_json = dir.path().join(format!("{model}.json"));
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_perpend"))
            .args(["calibrate", "--sensors", s.to_str().unwrap()])
            .args(["--poses", p.to_str().unwrap(), "--model", model])
            .args(["--out", out_json.to_str().unwrap()])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{model}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        ParamFile::read(&out_json).unwrap()
    };
    let table = calibrate("linearity_table");
    assert!(table.sensors.iter().all(|x| x
        .ext
        .linearity_table
        .is_some_and(|t| t.values_mm.iter().any(|v| *v != 0.0))));
    let back = ParamFile::parse(&serde_json::to_string(&table).unwrap(), "mem").unwrap();
    assert_eq!(back, table);
    let truth = &data.true_planes[100..];
    let eb = stored_head_error(&calibrate("base"), &test, truth);
    let ec = stored_head_error(&calibrate("nonlinearity"), &test, truth);
    let et = stored_head_error(&table, &test, truth);
    // Seed 21: table 0.0126°, cubic 0.0127°, paper's model 0.0276°.
    assert!(
        et < 0.6 * eb && et < 1.05 * ec,
        "table {et:.4}°, cubic {ec:.4}°, base {eb:.4}°"
    );
}

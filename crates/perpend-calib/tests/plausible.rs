//! Plausibility by physics (`perpend_formats::plausible`): the thresholds are
//! checked on the simulator's clean runs (every head of `perpend simulate`,
//! several seeds: nothing refused, nothing left out, no noise warning), and
//! each mistake of the issue is caught by name on the same runs.
#![allow(clippy::unwrap_used, missing_docs)]

use clap::Parser;
use perpend_calib::candidates::{self, Effect, Refs};
use perpend_calib::sim::{setup, simulate};
use perpend_core::calib::LsqConfig;
use perpend_formats::exchange::{PoseTable, SensorTable};
use perpend_formats::plausible::{check_run, check_units, sigma_warning};
use rand::rngs::StdRng;
use rand::SeedableRng;

#[derive(Parser)]
struct Sim {
    #[command(flatten)]
    a: perpend_calib::sim::Args,
}

/// A clean simulated run as `perpend simulate` writes it (σ declared =
/// the noise simulated).
fn run(head: &str, seed: u64) -> (SensorTable, PoseTable) {
    let s = seed.to_string();
    let a = Sim::parse_from(["sim", "--out", "unused", "--head", head, "--seed", &s]).a;
    let mut rng = StdRng::seed_from_u64(a.seed);
    let (mut h, cfg) = setup(&a, &mut rng).unwrap();
    h.sigma_mm = Some(a.zeta);
    let d = simulate(&h, &cfg, &[], &mut rng).unwrap();
    (d.sensors, d.poses)
}

const HEADS: [&str; 3] = ["paper", "experiment", "random"];
const SEEDS: [u64; 4] = [1, 2, 3, 4];

/// Residual RMS of each sensor after the paper's least-squares fit.
fn residuals(s: &SensorTable, p: &PoseTable) -> Vec<f64> {
    let nominal = s.sensors().unwrap();
    let refs = Refs::of(p);
    nominal
        .iter()
        .enumerate()
        .map(|(i, n)| {
            let t = refs.terms(Effect::None, i);
            candidates::fit(n, i, p, t, &LsqConfig::default())
                .unwrap()
                .rms
        })
        .collect()
}

#[test]
fn clean_simulated_runs_raise_nothing() {
    for head in HEADS {
        for seed in SEEDS {
            let (s, p) = run(head, seed);
            let n = p.rows.len();
            let (p, left, total) = check_run("poses.csv", &s, p).unwrap();
            assert!(left.is_empty(), "{head} seed {seed}: {left:?}");
            assert_eq!(p.rows.len(), n);
            assert!(total > 3 * n, "{head} seed {seed}: {total} readings");
            for (row, rms) in s.rows.iter().zip(residuals(&s, &p)) {
                let d = row.sigma_mm.unwrap();
                let w = sigma_warning("s", d, rms, "residual RMS", true);
                assert!(w.is_none(), "{head} seed {seed}: {w:?}");
                // And the margin: the declared σ is within 2× of the residual.
                assert!(d < 2.0 * rms, "{head} seed {seed}: σ {d} vs {rms}");
            }
        }
    }
}

fn scaled(p: &PoseTable, readings: f64, planes: f64) -> PoseTable {
    let mut p = p.clone();
    for r in &mut p.rows {
        for x in r.readings.iter_mut().flatten() {
            *x *= readings;
        }
        r.plane.d *= planes;
        r.abcd[3] *= planes;
    }
    p
}

#[test]
fn readings_and_planes_in_other_units_are_refused_by_name() {
    for head in HEADS {
        let (s, p) = run(head, 7);
        let cases = [
            (
                1.0 / 25.4,
                1.0,
                "the readings d1_mm … d4_mm: these look like inches",
            ),
            (
                1000.0,
                1.0,
                "the readings d1_mm … d4_mm: these look like micrometres",
            ),
            (1.0, 1.0 / 25.4, "the planes' d_mm: these look like inches"),
            (1.0, 1000.0, "the planes' d_mm: these look like micrometres"),
        ];
        for (r, q, want) in cases {
            // The experiment head's planes pass through the TCP (d ≈ 0 ±
            // 3 mm): an offset in inches moves the prediction by less than
            // the head's build tolerance, and is rightly not called wrong.
            if head == "experiment" && q < 1.0 {
                check_units("poses.csv", &s, &scaled(&p, r, q)).unwrap();
                continue;
            }
            let e = check_units("poses.csv", &s, &scaled(&p, r, q))
                .unwrap_err()
                .to_string();
            assert!(
                e.starts_with("poses.csv: ") && e.contains(want),
                "{head}: {e}"
            );
            assert!(e.contains("millimetres"), "{e}");
        }
        check_units("poses.csv", &s, &p).unwrap();
    }
}

#[test]
fn one_reading_a_hundred_times_too_large_is_named_not_a_blunder() {
    let (s, mut p) = run("paper", 3);
    let (k, pose, line) = (10, p.rows[10].pose, p.rows[10].line);
    let v = p.rows[k].readings[1].unwrap() * 100.0;
    p.rows[k].readings[1] = Some(v);
    let (q, left, _) = check_run("poses.csv", &s, p).unwrap();
    assert_eq!(left.len(), 1);
    let l = &left[0];
    assert_eq!((l.sensor, l.pose, l.line, l.value_mm), (2, pose, line, v));
    let text = l.to_string();
    assert!(
        text.contains("sensor 2") && text.contains(&format!("pose {pose}")),
        "{text}"
    );
    assert!(
        text.contains("0–") && text.contains("outside the sensor's range"),
        "{text}"
    );
    assert_eq!(q.rows[k].readings[1], None);
    // The pose keeps its three other readings and is no blunder.
    let nominal = s.sensors().unwrap();
    let out = perpend_calib::noise::reject(
        &nominal,
        &q,
        &LsqConfig::default(),
        &perpend_calib::candidates::available_models(&q),
    );
    assert!(out.iter().all(|o| o.pose != pose), "{out:?}");
}

#[test]
fn a_sigma_typed_in_micrometres_warns_with_both_numbers() {
    let (s, p) = run("experiment", 2);
    let rms = residuals(&s, &p);
    let w = sigma_warning("sensor 1", 10.0, rms[0], "residual RMS", true).unwrap();
    assert!(w.contains("sigma_mm 10 mm") && w.contains("µm"), "{w}");
}

/// `measure`: a 300 mm reading is named as out of range (not "surface faces
/// away"), readings in micrometres are refused by name, and a thermally
/// calibrated head warns about readings without `temp_c`.
#[test]
fn measure_names_impossible_readings_and_missing_columns() {
    use perpend_calib::measure::missing_columns;
    use perpend_formats::exchange::parse_readings;
    use perpend_formats::plausible::check_readings;
    let (s, _) = run("paper", 1);
    let text = "pose,d1_mm,d2_mm,d3_mm,d4_mm\n1,41,41,41,41\n2,41,300,41,41\n3,40,41,42,41\n";
    let mut t = parse_readings(text.as_bytes(), "r.csv", Some(4)).unwrap();
    let (left, total) = check_readings("r.csv", &s, &mut t).unwrap();
    assert_eq!(total, 12);
    let l = left[0].to_string();
    assert!(
        l.contains("sensor 2, pose 2 (line 3): reading 300 mm outside"),
        "{l}"
    );
    assert_eq!(t.rows[1].readings[1], None);
    let micro = "pose,d1_mm,d2_mm,d3_mm,d4_mm\n1,41000,41000,41000,41000\n";
    let mut t = parse_readings(micro.as_bytes(), "r.csv", Some(4)).unwrap();
    let e = check_readings("r.csv", &s, &mut t).unwrap_err().to_string();
    assert!(e.contains("these look like micrometres"), "{e}");
    let mut sensors = s.sensors().unwrap();
    assert!(missing_columns(&sensors, &t, "r.csv").is_empty());
    sensors[2].ext.thermal = 1e-3;
    let w = missing_columns(&sensors, &t, "r.csv");
    assert!(
        w[0].contains("thermal correction") && w[0].contains("temp_c"),
        "{w:?}"
    );
}

/// The range columns are read, written back, and decide the range.
#[test]
fn range_columns_round_trip_and_decide() {
    use perpend_formats::exchange::{parse_sensors, write_sensors};
    use perpend_formats::plausible::range_of;
    let text = "sensor,x_mm,y_mm,z_mm,m,n,q,range_min_mm,range_max_mm\n1,50,0,0,-0.5,0,0.866,20,70\n2,0,50,0,0,-0.5,0.866,,\n";
    let t = parse_sensors(text.as_bytes(), "s.csv").unwrap();
    let mut out = Vec::new();
    write_sensors(&mut out, &t, &[]).unwrap();
    let back = parse_sensors(out.as_slice(), "s.csv").unwrap();
    assert_eq!(back, t);
    let r = range_of(&t.rows[0]);
    assert_eq!((r.min_mm, r.max_mm, r.given), (20.0, 70.0, true));
    let r = range_of(&t.rows[1]);
    assert!(!r.given && (r.max_mm - 200.0).abs() < 0.5, "{r:?}");
}

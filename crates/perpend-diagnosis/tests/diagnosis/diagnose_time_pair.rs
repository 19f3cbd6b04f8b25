//! Drift and a warm-up that share the run's time axis (issue 35, item 3),
//! end to end through `diagnose()`: named together when the run reaches
//! the warm-up's plateau, said inseparable (with the run that would
//! separate them) when it ends on the rise. The decision's forward step
//! and nested test are in `diagnose/decision.rs` and `diagnose/nested.rs`;
//! these tests live here so that no stage's file imports the pass
//! (`host-tests/tests/diagnose_stages.rs`).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use perpend_calib::candidates::Effect;
use perpend_calib::lags::{separable, CONFOUNDED_R};
use perpend_calib::sim::timed_paper_run;
use perpend_diagnosis::diagnose::{diagnose, Settings};
use perpend_formats::exchange::{PoseTable, SensorTable};

/// A simulated run (paper head, 60 poses 30 s apart) with a linear
/// drift `A_i·t/t_end` and a reading tied to a head temperature that
/// warms as `21 + 6·tanh(t/τ)` (`k_i` mm/°C), τ a fraction `tau_frac`
/// of the run: 0.12 reaches the plateau by 36 % of the run, 1.2 ends on
/// the rise.
fn warm_drift_run(tau_frac: f64, seed: u64) -> (SensorTable, PoseTable) {
    let (head, mut run) = timed_paper_run(seed).unwrap();
    let t_end = run.rows.iter().filter_map(|r| r.t_s).fold(0.0, f64::max);
    let (a, k) = ([0.03, -0.025, 0.02, -0.03], [0.005, 0.006, -0.005, 0.004]);
    for row in &mut run.rows {
        let t = row.t_s.unwrap();
        let temp = 21.0 + 6.0 * (t / (tau_frac * t_end)).tanh();
        row.temp_c = Some(temp);
        for (i, r) in row.readings.iter_mut().enumerate() {
            if let Some(d) = r {
                *d += a[i] * t / t_end + k[i] * (temp - 21.0);
            }
        }
    }
    let table = SensorTable::from_sensors(&head.nominal, head.sigma_mm);
    (table, run)
}

/// With the plateau in the run (temperature against time r ≈ 0.6) the
/// drift and the warm-up are named together, on several draws, and the
/// JSON carries no `inseparable`.
#[test]
fn drift_and_a_warm_up_with_its_plateau_are_named_together() {
    for seed in [21, 22, 23] {
        let (table, run) = warm_drift_run(0.12, seed);
        assert!(separable(&run), "seed {seed}");
        let d = diagnose(&table, &run, &Settings::default()).unwrap();
        let named = d.effects();
        assert!(
            named.contains(&Effect::Thermal) && named.contains(&Effect::Drift),
            "seed {seed}: {named:?} ({:?})",
            d.decided.decision.reasons
        );
        assert!(d.json().inseparable.is_none(), "seed {seed}");
    }
}

/// Without the plateau (the run ends on the rise, r > 0.98) the two are
/// said inseparable: one of them named, the JSON key `inseparable`
/// present with the run that would separate them.
#[test]
fn drift_and_a_warm_up_without_plateau_are_said_inseparable() {
    for seed in [21, 22] {
        let (table, run) = warm_drift_run(1.2, seed);
        assert!(!separable(&run), "seed {seed}");
        let d = diagnose(&table, &run, &Settings::default()).unwrap();
        let named = d.effects();
        assert!(
            named.contains(&Effect::Thermal) || named.contains(&Effect::Drift),
            "seed {seed}: {named:?}"
        );
        let j = d.json().inseparable.unwrap();
        assert!(j.temp_time_r > CONFOUNDED_R, "seed {seed}: {j:?}");
        assert!(j.separated_by.contains("plateau"), "{j:?}");
    }
}

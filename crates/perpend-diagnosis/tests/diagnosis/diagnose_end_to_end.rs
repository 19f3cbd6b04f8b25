//! End-to-end tests of `perpend diagnose` that were in the test modules
//! of `diagnose/candidates.rs` and `diagnose/select.rs`: they run the
//! whole pass, so they live here and those files' tests import no later
//! file of the pass (`host-tests/tests/diagnose_stages.rs`).
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use perpend_calib::candidates::Effect;
use perpend_calib::sim::{add_sine_linearity, paper_head, simulate, Dataset, SimConfig, SimHead};
use perpend_diagnosis::diagnose::diagnose;
use rand::SeedableRng;

/// A simulated run of the paper's head: `poses` poses, seed `seed`.
fn paper_run(poses: usize, seed: u64) -> (SimHead, Dataset) {
    let head = paper_head().unwrap();
    let mut cfg = SimConfig::paper();
    cfg.poses = poses;
    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let run = simulate(&head, &cfg, &[], &mut rng).unwrap();
    (head, run)
}

/// A linearity error of a shape no candidate has (one sine period over
/// each sensor's range, as a triangulation sensor's residual
/// linearity often is), added to a simulated run: the table is named,
/// the held-out RMS comes within 10 % of the same run without the
/// error, and the cubic is refused as implausible.
#[test]
fn an_s_shaped_linearity_error_is_followed_by_the_table() {
    let (_, mut run) = paper_run(120, 11);
    let clean = run.clone();
    add_sine_linearity(&mut run.poses, &[0.06, -0.05, 0.055, -0.06]);
    let d = diagnose(&run.sensors, &run.poses, &Default::default()).unwrap();
    assert_eq!(d.effects(), vec![Effect::LinearityTable]);
    let floor = diagnose(&clean.sensors, &clean.poses, &Default::default())
        .unwrap()
        .scores
        .base
        .heldout_rms_mm;
    assert!(
        d.scores.extended.heldout_rms_mm < 1.1 * floor,
        "{} vs {floor}",
        d.scores.extended.heldout_rms_mm
    );
    // The polynomial follows the sine inside the run about as well on
    // held-out poses, but bends away beyond it: more than 1 mm at the
    // range ends, which no sensor does; the table is linear there.
    assert!(
        d.fits
            .implausible
            .iter()
            .any(|(e, _)| *e == Effect::Nonlinearity),
        "{:?}",
        d.fits.implausible
    );
}

/// Two effects at once, neither in the exact form of a candidate: a
/// per-sensor gain and an exponential settling drift (the candidate is
/// linear in time). Both are named, by forward selection, from the
/// measured run alone.
#[test]
fn two_effects_are_named_together() {
    let head = paper_head().unwrap();
    let mut cfg = SimConfig::paper();
    cfg.poses = 80;
    cfg.dt_s = Some(30.0);
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let mut data = simulate(&head, &cfg, &[], &mut rng).unwrap();
    let mean: Vec<f64> = (0..4)
        .map(|i| {
            let v: Vec<f64> = data
                .poses
                .rows
                .iter()
                .filter_map(|r| r.readings[i])
                .collect();
            v.iter().sum::<f64>() / v.len() as f64
        })
        .collect();
    let gain = [0.02, -0.015, 0.012, -0.02];
    let settle = [0.06, -0.05, 0.04, -0.06];
    for row in &mut data.poses.rows {
        let t = row.t_s.unwrap();
        for i in 0..4 {
            if let Some(d) = row.readings[i] {
                let drift = settle[i] * (1.0 - (-t / 900.0).exp());
                row.readings[i] = Some(d + gain[i] * (d - mean[i]) + drift);
            }
        }
    }
    let d = diagnose(&data.sensors, &data.poses, &Default::default()).unwrap();
    let named = d.effects();
    assert!(
        named.contains(&Effect::Gain)
            || named.contains(&Effect::Nonlinearity)
            || named.contains(&Effect::LinearityTable),
        "{named:?}"
    );
    assert!(named.contains(&Effect::Drift), "{named:?}");
    assert!(d.run.outliers.is_empty());
    // Both nulls come from the re-simulations: one per candidate, every
    // draw, and the rank z is its own statistic.
    let (g, r) = (&d.decided.expected.gain_z, &d.decided.expected.rank_z);
    assert_eq!(g.len(), r.len());
    assert!(!r.is_empty());
    for ((eg, sg), (er, sr)) in g.iter().zip(r) {
        assert_eq!(eg, er);
        assert_eq!(sr.n, d.decided.expected.draws, "{er:?}");
        assert_ne!((sg.mean, sg.sd), (sr.mean, sr.sd), "{er:?}");
    }
    // The floor is simulated at the noise left by both: the extended
    // model comes back to it.
    assert!(
        d.scores.extended.heldout_rms_mm < 1.15 * d.decided.floor_mm,
        "{} vs {}",
        d.scores.extended.heldout_rms_mm,
        d.decided.floor_mm
    );
}

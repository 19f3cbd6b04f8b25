//! The direction test of `perpend diagnose` (issue 35, item 4) end to end:
//! a simulated run whose readings lag each sensor's last move by twice the
//! reading noise is `unexplained` with the offset named; the same run
//! without the offset is not; its rows shuffled without `t_s` cannot be
//! tested and the report says so.
#![allow(clippy::unwrap_used, clippy::expect_used, clippy::panic, missing_docs)]

use perpend_calib::sim::{paper_head, simulate, Dataset, SimConfig};
use perpend_core::model::distance;
use perpend_diagnosis::diagnose::direction::DirectionTest;
use perpend_diagnosis::diagnose::{diagnose, Diagnosis};
use rand::seq::SliceRandom;
use rand::SeedableRng;

/// A 60-pose paper run (reading noise ζ = 10 µm, the paper's tracker),
/// rows in measurement order without `t_s`.
fn run(seed: u64) -> (Dataset, Vec<perpend_core::head::Sensor<f64>>) {
    run_with(seed, 1.0)
}

/// [`run`] with the tracker's point noise ξ times `tracker`.
fn run_with(seed: u64, tracker: f64) -> (Dataset, Vec<perpend_core::head::Sensor<f64>>) {
    let head = paper_head().unwrap();
    let mut cfg = SimConfig::paper();
    cfg.poses = 60;
    if let Some(t) = &mut cfg.tracker {
        t.xi_mm *= tracker;
    }
    let data = simulate(
        &head,
        &cfg,
        &[],
        &mut rand::rngs::StdRng::seed_from_u64(seed),
    )
    .unwrap();
    (data, head.truth)
}

/// Adds `−hᵢ·sign(dᵢ − dᵢ,prev)` to every reading (true distances, file
/// order; the first pose untouched).
fn add_hysteresis(data: &mut Dataset, truth: &[perpend_core::head::Sensor<f64>], h: &[f64]) {
    let mut prev: Option<Vec<f64>> = None;
    for row in &mut data.poses.rows {
        let d: Vec<f64> = (0..truth.len())
            .map(|i| distance(&truth[i], &row.plane, i).unwrap())
            .collect();
        if let Some(p) = &prev {
            for (i, r) in row.readings.iter_mut().enumerate() {
                let sign = if d[i] >= p[i] { 1.0 } else { -1.0 };
                *r = r.map(|v| v - h[i] * sign);
            }
        }
        prev = Some(d);
    }
}

fn diag(data: &Dataset) -> Diagnosis {
    diagnose(&data.sensors, &data.poses, &Default::default()).unwrap()
}

/// Twice the reading noise (ζ = 10 µm), a different size per sensor.
const H_MM: [f64; 4] = [0.02, 0.016, 0.024, 0.02];

#[test]
fn offset_at_twice_the_noise_is_named_unexplained_with_its_size() {
    let (mut data, truth) = run(11);
    add_hysteresis(&mut data, &truth, &H_MM);
    let d = diag(&data);
    assert_eq!(
        d.decided.effect.name(),
        "unexplained",
        "{:?}",
        d.decided.direction
    );
    assert!(d.effects().is_empty());
    let DirectionTest::Tested(t) = &d.decided.direction else {
        panic!("not tested: {:?}", d.decided.direction)
    };
    assert!(t.found && t.p < t.level, "{t:?}");
    assert_eq!(t.order.name(), "file order");
    for (s, h) in t.sensors.iter().zip(H_MM) {
        let s = s.expect("every sensor has its moves");
        // within 4σ (plus 3 µm of what the nominal fit takes up)
        assert!(
            (s.h_mm - h).abs() < 4.0 * s.sigma_mm + 0.003,
            "{s:?} vs {h}"
        );
    }
    let j = d.json();
    let o = j.direction_offset.expect("the JSON names it");
    assert_eq!(o.order, "file order");
    assert_eq!(o.h_mm.len(), 4);
}

#[test]
fn same_run_without_the_offset_is_not_named() {
    let (data, _) = run(11);
    let d = diag(&data);
    assert_eq!(d.decided.effect.name(), "none", "{:?}", d.decided.direction);
    assert!(!d.decided.direction.found(), "{:?}", d.decided.direction);
    assert!(d.json().direction_offset.is_none());
}

#[test]
fn a_large_tracker_noise_is_not_a_direction_effect() {
    // ξ × 3: a per-pose plane error of about 6× the reading noise, shared
    // by the sensors of a pose, leaks into the signs of small moves only.
    for seed in 21..24 {
        let (data, _) = run_with(seed, 3.0);
        let d = diag(&data);
        assert!(
            !d.decided.direction.found(),
            "seed {seed}: {:?}",
            d.decided.direction
        );
        assert!(matches!(d.decided.direction, DirectionTest::Tested(_)));
    }
}

#[test]
fn shuffled_rows_without_time_cannot_be_tested() {
    let (mut data, truth) = run(11);
    add_hysteresis(&mut data, &truth, &H_MM);
    data.poses
        .rows
        .shuffle(&mut rand::rngs::StdRng::seed_from_u64(5));
    let d = diag(&data);
    let DirectionTest::Untestable(why) = &d.decided.direction else {
        panic!("tested on shuffled rows: {:?}", d.decided.direction)
    };
    assert!(why.contains("order of the moves is unknown"), "{why}");
    assert!(d.decided.direction.line().contains("cannot test"));
    assert!(d.json().direction_offset.is_none());
}

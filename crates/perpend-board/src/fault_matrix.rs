//! The sensor part of the fault matrix (issue 7 item 3), through the
//! pipeline exactly as the board runs it. Each test names the fault and
//! asserts the documented outcome: status bits, and never a wrong normal
//! reported as valid. (Flash faults: `storage` and `app` tests; EMCY:
//! `app` tests.)

use crate::pipeline::testutil::*;
use crate::pipeline::{Output, Pipeline, Sample};
use crate::status::*;
use perpend_core::params::Params;

/// A wrong normal: further than this from the truth [deg]. The factory
/// residual limit (0.05 mm) bounds the tilt error of one bad sensor among
/// four to 2·0.05 mm / 27 mm (spot radius) = 0.21°.
const WRONG_DEG: f64 = 0.25;

/// Deterministic noise in [-1, 1).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }
}

fn check_never_wrong(o: &Output) {
    if o.valid() {
        let e = normal_error_deg(o, &test_plane());
        assert!(e < WRONG_DEG, "valid but {e}° off: {o:?}");
    } else {
        assert_eq!(o.normal, [0.0; 3]);
    }
}

fn run(pl: &mut Pipeline, counts: [u16; 4]) -> Output {
    let o = pl.process(&sample(counts));
    check_never_wrong(&o);
    o
}

/// Each sensor in turn with its loop current at `ma`: the sensor's nibble
/// shows `bit`, the plane falls back to three sensors (bit 16) and stays
/// right.
fn single_sensor_current(ma: f32, bit: u32) {
    for i in 0..4 {
        let mut pl = pipeline();
        let p = *pl.params();
        let mut c = counts_for_plane(&p, &test_plane());
        c[i] = counts_for_ma(&p, i, ma);
        let o = run(&mut pl, c);
        assert_eq!(sensor_nibble(o.status, i), bit, "sensor {i}");
        assert!(o.valid());
        assert_eq!(o.status & DEGRADED, DEGRADED);
        assert_eq!(o.used(), 3);
        assert!(normal_error_deg(&o, &test_plane()) < 0.05);
    }
}

#[test]
fn each_sensor_open_loop() {
    single_sensor_current(0.0, SENSOR_OPEN_LOOP);
    single_sensor_current(3.5, SENSOR_OPEN_LOOP);
}

#[test]
fn each_sensor_overcurrent() {
    single_sensor_current(21.5, SENSOR_OVERCURRENT);
}

#[test]
fn each_sensor_saturated() {
    single_sensor_current(3.7, SENSOR_OUT_OF_RANGE);
    single_sensor_current(20.8, SENSOR_OUT_OF_RANGE);
}

#[test]
fn two_sensors_lost_means_no_plane() {
    for a in 0..4 {
        for b in a + 1..4 {
            let mut pl = pipeline();
            let p = *pl.params();
            let mut c = counts_for_plane(&p, &test_plane());
            c[a] = counts_for_ma(&p, a, 1.0);
            c[b] = counts_for_ma(&p, b, 22.0);
            let o = run(&mut pl, c);
            assert!(!o.valid());
            assert_eq!(o.status & NO_PLANE, NO_PLANE);
            assert_eq!(sensor_nibble(o.status, a), SENSOR_OPEN_LOOP);
            assert_eq!(sensor_nibble(o.status, b), SENSOR_OVERCURRENT);
        }
    }
}

#[test]
fn each_sensor_stuck_at_a_constant() {
    let p = Params::factory();
    let limit = p.acq.stuck_samples as usize;
    for i in 0..4 {
        let mut pl = Pipeline::new(p, true);
        let base = counts_for_plane(&p, &test_plane());
        let mut rng = Lcg(i as u64 + 1);
        for k in 0..limit + 10 {
            // live sensors: ±2 counts of noise (±2/65520 of the span)
            let mut c = base;
            for (j, v) in c.iter_mut().enumerate() {
                if j != i {
                    *v = (*v as f32 + 2.0 * rng.next()).round() as u16;
                }
            }
            let o = run(&mut pl, c);
            if k < limit {
                assert_eq!(o.status & SENSOR_STUCK, 0, "sensor {i}, sample {k}");
                assert_eq!(o.used(), 4, "sample {k}");
            } else {
                assert_eq!(o.status & SENSOR_STUCK, SENSOR_STUCK, "sensor {i}");
                assert_eq!(sensor_nibble(o.status, i), 0);
                assert_eq!(o.status & DEGRADED, DEGRADED);
                assert!(o.valid());
            }
        }
    }
}

#[test]
fn each_sensor_noisy() {
    // One sensor with ±0.3 mm of noise: samples are either valid within
    // the bound (jump detector drops the big steps, the residual check
    // the big offsets) or flagged; both kinds occur.
    for i in 0..4 {
        let mut pl = pipeline();
        let p = *pl.params();
        let truth = mm_for_plane(&p, &test_plane());
        let mut rng = Lcg(100 + i as u64);
        let (mut valid, mut flagged) = (0, 0);
        for _ in 0..2000 {
            let mut mm = truth;
            mm[i] += 0.3 * rng.next();
            let o = run(&mut pl, counts_for_mm(&p, mm));
            if o.valid() {
                valid += 1;
            } else {
                assert_eq!(o.status & RESIDUAL_HIGH, RESIDUAL_HIGH);
                flagged += 1;
            }
        }
        assert!(
            valid > 100 && flagged > 100,
            "{valid} valid, {flagged} flagged"
        );
    }
}

#[test]
fn spatter_jump_drops_the_sensor_for_the_hold_time() {
    let p = Params::factory();
    let hold = p.acq.jump_hold as usize;
    for i in 0..4 {
        let mut pl = Pipeline::new(p, true);
        let truth = mm_for_plane(&p, &test_plane());
        for _ in 0..5 {
            assert_eq!(run(&mut pl, counts_for_mm(&p, truth)).used(), 4);
        }
        // spatter: +3 mm for 5 samples under spot i
        for k in 0..5 {
            let mut mm = truth;
            mm[i] += 3.0;
            let o = run(&mut pl, counts_for_mm(&p, mm));
            assert_eq!(sensor_nibble(o.status, i), 0, "sample {k}");
            assert!(o.valid() && o.status & DEGRADED != 0);
            assert!(normal_error_deg(&o, &test_plane()) < 0.05);
        }
        // back to the surface: a jump again, held out, then used
        let mut back_at = None;
        for k in 0..hold + 5 {
            let o = run(&mut pl, counts_for_mm(&p, truth));
            if o.used() == 4 && back_at.is_none() {
                back_at = Some(k);
            }
        }
        assert_eq!(back_at, Some(hold), "sensor {i}");
    }
}

#[test]
fn hole_edge_step_is_never_a_wrong_valid_normal() {
    // A permanent +1.5 mm step under one spot (the spot fell into a hole):
    // dropped for the hold time, then the four-sensor residual flags it.
    let p = Params::factory();
    for i in 0..4 {
        let mut pl = Pipeline::new(p, true);
        let truth = mm_for_plane(&p, &test_plane());
        run(&mut pl, counts_for_mm(&p, truth));
        let mut mm = truth;
        mm[i] += 1.5;
        let mut last = Output::default();
        for _ in 0..100 {
            last = run(&mut pl, counts_for_mm(&p, mm));
        }
        assert_eq!(
            last.status & (RESIDUAL_HIGH | NO_PLANE),
            RESIDUAL_HIGH | NO_PLANE
        );
    }
}

#[test]
fn rigid_approach_is_not_a_jump() {
    // The head approaches the surface at 1 mm per sample (1 m/s at 1 kHz):
    // all readings change together, no sensor is dropped.
    let p = Params::factory();
    let mut pl = Pipeline::new(p, true);
    for k in 0..20 {
        let plane =
            perpend_core::geometry::Plane::from_abcd(0.035, -0.052, 1.0, -(50.0 - k as f64))
                .expect("plane");
        let o = pl.process(&sample(counts_for_plane(&p, &plane)));
        assert_eq!(o.used(), 4, "sample {k}");
        assert!(o.valid());
        assert!(normal_error_deg(&o, &plane) < 0.05);
    }
}

#[test]
fn all_faults_at_once_stay_nan_free() {
    let p = Params::factory();
    let mut pl = Pipeline::new(p, false);
    let c = [
        counts_for_ma(&p, 0, 0.0),
        counts_for_ma(&p, 1, 25.0),
        counts_for_ma(&p, 2, 3.7),
        u16::MAX,
    ];
    let o = pl.process(&Sample {
        counts: c,
        temp_c: Some(f32::NAN),
        t_s: None,
    });
    assert_eq!(
        o.status,
        UNCALIBRATED
            | NO_PLANE
            | sensor_bits(0, SENSOR_OPEN_LOOP)
            | sensor_bits(1, SENSOR_OVERCURRENT)
            | sensor_bits(2, SENSOR_OUT_OF_RANGE)
            | sensor_bits(3, SENSOR_OVERCURRENT)
    );
    assert!(o.readings_mm.iter().all(|v| v.is_finite()));
}

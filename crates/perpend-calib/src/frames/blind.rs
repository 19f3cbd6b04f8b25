//! The frame estimate on reversal runs from an independent generator
//! (issue 46 item 4).
//!
//! The generator shares no code with the estimator's model ([`super::true_plane`],
//! [`super::readings`], `perpend_core::model`, `crate::sim`): its own head
//! (four beams on a 30° cone at 0/90/180/270° about the spindle, zero
//! points on a 38 mm ring 12 mm behind the TCP; not the paper's head), its
//! own robot (the spindle axis held through one point of the datum plate,
//! the head tilted about the plate's x then y by up to ±10° and turned
//! about the spindle by the last joint), its own ray/plane intersection
//! and its own noise (SplitMix64, Box-Muller). The tracker's frame is
//! tilted by `ε` against the robot base about the plate point it was
//! registered on, so it reports the plate turned by `−ε`. Shared are only
//! the estimator's inputs, what `perpend frames` reads from a run's files:
//! the nominal head ([`Sensor`]), the tracker's plane in the taught TCS
//! ([`Plane`]) and the joint angle ([`FramePose::seen`]).
//!
//! Frames: the datum frame has z along the plate's inward normal, the
//! direction the spindle looks at the level pose; the TCS has z along the
//! spindle towards the plate.
//!
//! Claims checked, at 4 µm with 48 poses, 10 µm with 64 and 20 µm with 96
//! (at 0/90/180/270°): a 0.05° tracker tilt is within 2σ of the truth in
//! ≥ 90 % of the runs and warned (significant and above the calibration's
//! expected normal error) in every run; without a tilt the estimates
//! called significant are ≤ 5 % (plus the binomial margin of the count).
//! Not claimed: at 20 µm with 48 or 64 poses the calibration's expected
//! normal error (a bootstrap of the head-only fit, 0.030-0.049° there) is
//! close to the tilt itself, and the warning came in 27 and 28 of 30 runs
//! (seeds 46,400,000-029; the estimate within 2σ in 27 of 30).

use super::report::summarise;
use super::*;
use crate::accuracy::{base_refit, expected_normal_error};
use perpend_formats::exchange::{PoseRow, PoseTable};

type V3 = [f64; 3];
type M3 = [[f64; 3]; 3];

fn mul(a: &M3, b: &M3) -> M3 {
    core::array::from_fn(|i| core::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

fn apply(a: &M3, v: &V3) -> V3 {
    core::array::from_fn(|i| (0..3).map(|k| a[i][k] * v[k]).sum())
}

fn transpose(a: &M3) -> M3 {
    core::array::from_fn(|i| core::array::from_fn(|j| a[j][i]))
}

fn dot(a: &V3, b: &V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn add(a: &V3, b: &V3, k: f64) -> V3 {
    [a[0] + k * b[0], a[1] + k * b[1], a[2] + k * b[2]]
}

/// Rotation by `t` about axis `axis` (0 = x, 1 = y, 2 = z).
fn rot(axis: usize, t: f64) -> M3 {
    let (c, s) = (t.cos(), t.sin());
    let (i, j) = ((axis + 1) % 3, (axis + 2) % 3);
    let mut m = [[0.0; 3]; 3];
    m[axis][axis] = 1.0;
    m[i][i] = c;
    m[j][j] = c;
    m[i][j] = -s;
    m[j][i] = s;
    m
}

/// Rotation by the rotation vector `w` (Rodrigues).
fn rodrigues(w: &V3) -> M3 {
    let a = dot(w, w).sqrt();
    if a < 1e-300 {
        return rot(0, 0.0);
    }
    let k = [w[0] / a, w[1] / a, w[2] / a];
    let kx: M3 = [[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]];
    let k2 = mul(&kx, &kx);
    core::array::from_fn(|i| {
        core::array::from_fn(|j| {
            let id = if i == j { 1.0 } else { 0.0 };
            id + a.sin() * kx[i][j] + (1.0 - a.cos()) * k2[i][j]
        })
    })
}

/// SplitMix64 with uniform and normal draws.
struct Draw(u64);

impl Draw {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in (0, 1).
    fn unit(&mut self) -> f64 {
        ((self.next() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn within(&mut self, half: f64) -> f64 {
        half * (2.0 * self.unit() - 1.0)
    }
    fn normal(&mut self) -> f64 {
        let (u, v) = (self.unit(), self.unit());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

/// A beam: zero point and unit direction in the TCS.
type Beam = (V3, V3);

/// The head: four beams on a 30° cone, zero points on a 38 mm ring at
/// 0/90/180/270°, 12 mm behind the TCP, converging on the spindle axis.
fn nominal_beams() -> Vec<Beam> {
    let (ring, cone, back) = (38.0, 30f64.to_radians(), 12.0);
    (0..4)
        .map(|i| {
            let phi = std::f64::consts::FRAC_PI_2 * i as f64;
            let zero = [ring * phi.cos(), ring * phi.sin(), -back];
            let dir = [-cone.sin() * phi.cos(), -cone.sin() * phi.sin(), cone.cos()];
            (zero, dir)
        })
        .collect()
}

/// The true head: zero points off by up to ±0.5 mm, beams turned by up to
/// ±10 mrad about x and y.
fn true_beams(nominal: &[Beam], g: &mut Draw) -> Vec<Beam> {
    nominal
        .iter()
        .map(|(z, d)| {
            let zero = [
                z[0] + g.within(0.5),
                z[1] + g.within(0.5),
                z[2] + g.within(0.5),
            ];
            let t = mul(&rot(0, g.within(0.01)), &rot(1, g.within(0.01)));
            (zero, apply(&t, d))
        })
        .collect()
}

/// A generated run: the nominal head, the estimator's poses (the
/// tracker's planes in the taught TCS with the joint angles) and readings.
struct Run {
    nominal: Vec<Sensor<f64>>,
    poses: Vec<FramePose>,
    readings: Vec<Vec<Option<f64>>>,
}

/// A run of `poses` poses (`poses / 4` planned tilts, each at the joint's
/// 0/90/180/270°), reading noise `sigma_mm`, tracker tilt `eps` [rad]
/// about the datum's x and y.
fn generate(seed: u64, poses: usize, sigma_mm: f64, eps: [f64; 2]) -> Run {
    let mut g = Draw(seed);
    let nominal = nominal_beams();
    let truth = true_beams(&nominal, &mut g);
    // the plate: through the datum's origin, normal -z (towards the head)
    let m: V3 = [0.0, 0.0, -1.0];
    let reported = apply(&transpose(&rodrigues(&[eps[0], eps[1], 0.0])), &m);
    let mut run = Run {
        nominal: nominal
            .iter()
            .map(|(z, d)| Sensor::new((*z).into(), (*d).into()).unwrap())
            .collect(),
        poses: Vec::new(),
        readings: Vec::new(),
    };
    for _ in 0..poses / 4 {
        let (a, b) = (g.within(10f64.to_radians()), g.within(10f64.to_radians()));
        let standoff = 36.0 + g.within(4.0);
        for k in 0..4 {
            let theta = std::f64::consts::FRAC_PI_2 * k as f64;
            // the TCS in the datum frame, its origin on the spindle axis
            let r = mul(&mul(&rot(0, a), &rot(1, b)), &rot(2, theta));
            let origin = add(&[0.0; 3], &apply(&r, &[0.0, 0.0, 1.0]), -standoff);
            let row = truth
                .iter()
                .map(|(z, d)| {
                    let e = add(&origin, &apply(&r, z), 1.0);
                    let u = apply(&r, d);
                    // beam e + t·u meets m·x = 0 (the plate through the origin)
                    let t = -dot(&m, &e) / dot(&m, &u);
                    Some(t + sigma_mm * g.normal())
                })
                .collect();
            // the tracker's plane in the taught TCS: normal Rᵀ·reported,
            // through the spindle's point on the plate (0, 0, standoff)
            let n = apply(&transpose(&r), &reported);
            let plane = Plane {
                n: n.into(),
                d: -n[2] * standoff,
            };
            run.poses.push(FramePose::seen(&plane, theta));
            run.readings.push(row);
        }
    }
    run
}

/// The calibration's expected normal error [deg] of a run (what `cell
/// run` weighs frame errors against): the bootstrap of the head-only fit
/// over the run's poses, 20 resamples.
fn expected_deg(run: &Run) -> f64 {
    let plain = estimate(&run.nominal, &run.poses, &run.readings, None).unwrap();
    let rows = run
        .poses
        .iter()
        .zip(&run.readings)
        .enumerate()
        .map(|(k, (p, r))| PoseRow {
            line: 0,
            pose: k as i64 + 1,
            abcd: [p.plane.n.x, p.plane.n.y, p.plane.n.z, p.plane.d],
            plane: p.plane,
            readings: r.clone(),
            t_s: None,
            temp_c: None,
            noise: Default::default(),
        })
        .collect();
    let table = PoseTable { n_sensors: 4, rows };
    expected_normal_error(&plain.head, &table, &base_refit(&run.nominal), 20, 1)
        .unwrap()
        .rms_deg
}

/// The regimes: reading noise [mm] and poses.
const REGIMES: [(f64, usize); 3] = [(0.004, 48), (0.010, 64), (0.020, 96)];
const TILT_DEG: f64 = 0.05;

/// What `seeds` runs of one regime with a tracker tilt `TILT_DEG` about x
/// give: estimates within 2σ of the truth, runs warned with the fix.
fn tilted(sigma_mm: f64, poses: usize, seeds: std::ops::Range<u64>) -> (usize, usize, String) {
    let eps = [TILT_DEG.to_radians(), 0.0];
    let (mut inside, mut warned, mut log) = (0, 0, String::new());
    for seed in seeds {
        let run = generate(seed, poses, sigma_mm, eps);
        let expected = expected_deg(&run);
        let tol = Tolerance::expected(expected);
        let fit = estimate(&run.nominal, &run.poses, &run.readings, Some(tol)).unwrap();
        let (x, s) = (fit.frames[0], fit.sigma[0].unwrap());
        inside += usize::from((x - eps[0]).abs() <= 2.0 * s);
        let joints: Vec<f64> = run.poses.iter().map(|p| p.joint_rad.to_degrees()).collect();
        let rep = summarise(&fit, &joints, expected);
        warned += usize::from(
            rep.warnings
                .iter()
                .any(|w| w.starts_with("tracker tilt x") && w.contains("re-register the tracker")),
        );
        log += &format!(
            "seed {seed}: {:.0} ± {:.0} µrad, expected {expected:.4}°, resolved {}\n",
            1e6 * x,
            1e6 * s,
            fit.resolved[0]
        );
    }
    (inside, warned, log)
}

/// A 0.05° tracker tilt about x, 20 seeds per regime: within 2σ of the
/// truth in at least 54 of the 60 runs (90 %) and 16 of each regime's 20,
/// and warned with the fix in every run. If the 1σ is right (95.4 % within
/// 2σ) the 60 runs miss the 90 % in 2 % of seed sets; if it is 1.5× too
/// small (82 %), in 93 %.
#[test]
fn independent_generator_tilt_within_two_sigma_and_warned() {
    let mut all = 0;
    for (r, &(sigma_mm, poses)) in REGIMES.iter().enumerate() {
        let first = 46_400_000 + 100 * r as u64;
        let (inside, warned, log) = tilted(sigma_mm, poses, first..first + 20);
        assert!(
            inside >= 16 && warned == 20,
            "{sigma_mm} mm, {poses} poses: within 2σ {inside}/20, warned {warned}/20\n{log}"
        );
        all += inside;
    }
    assert!(all >= 54, "within 2σ {all}/60");
}

/// Without a tilt, 40 seeds per regime, two tilts each: 240 estimates, of
/// which a 2σ test calls 4.6 % (11) significant if the 1σ is right. The
/// claim is ≤ 5 %: it fails when the count exceeds 5 % by more than two
/// binomial standard deviations at 5 % (12 + 6.8: more than 18, 7.5 %); a
/// 1σ underestimated by 1.25× (11 % significant, 26 expected) fails.
#[test]
fn independent_generator_without_tilt_at_most_5_percent_significant() {
    let (mut significant, mut total) = (0, 0);
    for (r, &(sigma_mm, poses)) in REGIMES.iter().enumerate() {
        for k in 0..40u64 {
            let seed = 46_500_000 + 100 * r as u64 + k;
            let run = generate(seed, poses, sigma_mm, [0.0; 2]);
            let fit = estimate(
                &run.nominal,
                &run.poses,
                &run.readings,
                Some(Tolerance::fallback()),
            )
            .unwrap();
            for j in 0..2 {
                assert!(fit.sigma[j].is_some(), "seed {seed}: {:?}", fit.sigma);
                total += 1;
                significant += usize::from(fit.significant[j]);
            }
        }
    }
    assert_eq!(total, 240);
    assert!(significant <= 18, "{significant}/{total} significant");
}

//! Test data for the calibration tests: the paper's head (Chen Table 2 in
//! the +z-feed TCS) and seeded random calibration runs.

use nalgebra::{SVector, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

use super::CalPose;
use crate::ext::Context;
use crate::geometry::Plane;
use crate::head::{Head4, Sensor};
use crate::model::distance;

/// Nominal and true head of Chen Table 2, rotated 180° about x.
pub fn paper_heads() -> (Head4<f64>, Head4<f64>) {
    let nominal = [
        [50.0, 0.0, 0.0, -0.5, 0.0, -0.866],
        [0.0, 50.0, 0.0, 0.0, -0.5, -0.866],
        [-50.0, 0.0, 0.0, 0.5, 0.0, -0.866],
        [0.0, -50.0, 0.0, 0.0, 0.5, -0.866],
    ];
    let errors = [
        [1.3, 0.9, 1.1, 0.0445, 0.0506, -0.0228],
        [1.3, -1.4, 1.6, -0.0634, 0.0479, -0.0237],
        [1.3, -1.2, 1.2, -0.0507, -0.0365, -0.0266],
        [1.5, 1.1, 1.4, 0.0339, -0.0682, -0.0353],
    ];
    let rot = |v: [f64; 3]| Vector3::new(v[0], -v[1], -v[2]);
    let mk = |k: f64| {
        Head4::new(core::array::from_fn(|i| {
            let (n, e) = (nominal[i], errors[i]);
            Sensor::new(
                rot([n[0] + k * e[0], n[1] + k * e[1], n[2] + k * e[2]]),
                rot([n[3] + k * e[3], n[4] + k * e[4], n[5] + k * e[5]]),
            )
            .unwrap()
        }))
    };
    (mk(0.0), mk(1.0))
}

/// A random head: the nominal cone head with zero-point errors up to
/// ±1.5 mm and beam tilts up to ±0.07 rad.
pub fn random_heads(rng: &mut StdRng) -> (Head4<f64>, Head4<f64>) {
    let nominal = Head4::cone(50.0, 30f64.to_radians(), 0.0, 0.0).unwrap();
    let truth = Head4::new(core::array::from_fn(|i| {
        let mut u = || rng.gen_range(-1.0..=1.0);
        let d = SVector::<f64, 5>::from([1.5 * u(), 1.5 * u(), 1.5 * u(), 0.07 * u(), 0.07 * u()]);
        nominal.sensors[i].retract(&d).unwrap()
    }));
    (nominal, truth)
}

/// The plane with deviation angles `tx`, `ty` [deg] crossing the axis at
/// `standoff` [mm].
pub fn plane(tx: f64, ty: f64, standoff: f64) -> Plane<f64> {
    let n = Vector3::new(-ty.to_radians().tan(), tx.to_radians().tan(), -1.0).normalize();
    Plane {
        n,
        d: -n.z * standoff,
    }
}

/// Spread of a run: centre tilts [deg], full tilt ranges [deg], centre and
/// range of the standoff [mm].
#[derive(Clone, Copy)]
pub struct Spread {
    pub cx: f64,
    pub cy: f64,
    pub rx: f64,
    pub ry: f64,
    pub s: f64,
    pub rs: f64,
}

/// The paper reproduction's spread (Table 1 orientation, see perpend-diagnosis's
/// `PoseSpread::paper`).
pub const PAPER: Spread = Spread {
    cx: 17.888,
    cy: -1.042,
    rx: 10.0,
    ry: 10.0,
    s: 28.0,
    rs: 3.0,
};

/// `n` poses of `truth` with reading noise `zeta` [mm] (exact planes).
pub fn run(
    truth: &Head4<f64>,
    spread: Spread,
    n: usize,
    zeta: f64,
    seed: u64,
) -> Vec<CalPose<f64, 4>> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..n)
        .map(|_| {
            let mut u = || rng.gen_range(-0.5..=0.5);
            let p = plane(
                spread.cx + spread.rx * u(),
                spread.cy + spread.ry * u(),
                spread.s + spread.rs * u(),
            );
            let readings = core::array::from_fn(|i| {
                let e: f64 = rng.sample(StandardNormal);
                Some(distance(&truth.sensors[i], &p, i).unwrap() + zeta * e)
            });
            CalPose {
                plane: p,
                readings,
                ctx: Context::default(),
            }
        })
        .collect()
}

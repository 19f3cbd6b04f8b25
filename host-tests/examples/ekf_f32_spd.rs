//! Measurement behind the EKF finding of `/work/notes/reliability.md`: how
//! often the f32 covariance of `perpend_core::calib::Ekf` stops being
//! symmetric positive definite within 10,000 updates, per prior and
//! covariance form (20 random heads × 4 sensors each).
//!
//! ```text
//! cargo run --release -p host-tests --example ekf_f32_spd
//! ```
#![allow(missing_docs, clippy::unwrap_used)]

use nalgebra::{Cholesky, SVector, Vector3};
use perpend_core::calib::{CovarianceUpdate, Ekf, EkfConfig};
use perpend_core::geometry::Plane;
use perpend_core::head::Head4;
use perpend_core::model::distance;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;

fn datum(tx: f64, ty: f64, standoff: f64) -> Plane<f64> {
    let n = Vector3::new(-ty.to_radians().tan(), tx.to_radians().tan(), -1.0).normalize();
    Plane {
        n,
        d: -n.z * standoff,
    }
}

fn main() {
    let nominal = Head4::cone(50.0, 30f64.to_radians(), 0.0, 0.0).unwrap();
    let tolerance = SVector::<f32, 6>::from([2.25, 2.25, 2.25, 4.9e-3, 4.9e-3, 4.9e-3]);
    println!(
        "prior, noise (paper section), covariance form: runs that lost SPD / runs, refused updates"
    );
    for (prior, p0) in [
        ("P0 = I (paper)", None),
        ("P0 = tolerances^2", Some(tolerance)),
    ] {
        for (noise, base) in [
            (
                "R 8e-5, Q 1e-10 (sec. 5)",
                EkfConfig::<f32>::chen_simulation(),
            ),
            (
                "R 9e-6, Q 1e-12 (sec. 6)",
                EkfConfig::<f32>::chen_experiment(),
            ),
        ] {
            for form in [CovarianceUpdate::Paper, CovarianceUpdate::Joseph] {
                let (mut lost, mut runs, mut refused, mut min_ev) = (0, 0, 0u64, f64::MAX);
                for seed in 0..20u64 {
                    let mut rng = StdRng::seed_from_u64(seed);
                    let truth = Head4::new(core::array::from_fn(|i| {
                        let mut u = || rng.gen_range(-1.0..=1.0);
                        let d = SVector::<f64, 5>::from([
                            1.5 * u(),
                            1.5 * u(),
                            1.5 * u(),
                            0.07 * u(),
                            0.07 * u(),
                        ]);
                        nominal.sensors[i].retract(&d).unwrap()
                    }));
                    for i in 0..4 {
                        let mut cfg = base;
                        cfg.delta = 0.0;
                        cfg.covariance = form;
                        if let Some(p) = p0 {
                            cfg.p0 = p;
                        }
                        let mut ekf = Ekf::new(&nominal.sensors[i].cast::<f32>(), i, cfg).unwrap();
                        let mut bad = false;
                        for k in 0..10_000 {
                            let p = datum(
                                rng.gen_range(-10.0..10.0),
                                rng.gen_range(-10.0..10.0),
                                rng.gen_range(25.0..31.0),
                            );
                            let e: f64 = rng.sample(StandardNormal);
                            let d = distance(&truth.sensors[i], &p, i).unwrap() + 0.01 * e;
                            let p32 = Plane {
                                n: p.n.cast::<f32>(),
                                d: p.d as f32,
                            };
                            if ekf.update(&p32, d as f32).is_err() {
                                refused += 1;
                            }
                            if k < 200 || k % 10 == 0 {
                                let c = *ekf.covariance();
                                let ev = c.cast::<f64>().symmetric_eigen().eigenvalues.min();
                                min_ev = min_ev.min(ev);
                                bad |= Cholesky::new(c).is_none() || !(ev > 0.0);
                            }
                        }
                        runs += 1;
                        lost += usize::from(bad);
                    }
                }
                println!(
                    "{prior}, {noise}, {form:?}: {lost}/{runs} lost SPD, {refused} of {} updates refused, min eigenvalue {min_ev:.2e}",
                    runs * 10_000
                );
            }
        }
    }
}

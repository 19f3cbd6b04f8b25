//! Expected angular accuracy of a calibrated head over a run's poses: how
//! far the normal measured with this calibration may be off because the
//! run's noise made the parameters uncertain.
//!
//! The estimate is a bootstrap over poses: the run's poses are drawn with
//! replacement, the head is fitted again on each draw (the caller's fit,
//! so extensions are included), and each refitted head measures noise-free
//! readings of every pose's plane (as the fitted head predicts them)
//! through the board's own code ([`perpend_core::normal::plane`], Chen eq.
//! 18-19); the angle to that plane's normal is the error a calibration that
//! far off would make. Resampling whole poses keeps what the sensors share
//! in a pose (the tracker's plane error), which propagating each sensor's
//! own covariance would lose: that route overstated the error about 2× on
//! the paper's simulation, where the shared plane error moves all zero
//! points together and tilts no normal. The RMS over draws and poses is the
//! 1σ-equivalent, the 95th percentile the figure a cell engineer plans with.
//!
//! Limits: it holds over the run's own pose range, not beyond it; the
//! reading noise at measurement time is not included (it adds the noise
//! floor, see `perpend bench accuracy`); a run with a few dozen poses gives
//! a rough figure (the bootstrap's own spread); four-sensor heads only
//! (the board's). A draw whose refit fails (a resample that cannot
//! identify a parameter) is skipped and counted.

use anyhow::{anyhow, bail, Result};
use nalgebra::Vector3;
use perpend_core::calib::{LsqConfig, Poses};
use perpend_core::ext::Context;
use perpend_core::geometry::Plane;
use perpend_core::head::{Head4, Sensor};
use perpend_core::model::distance;
use perpend_core::normal::{plane, Method};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::candidates::Subset;
use perpend_formats::exchange::PoseTable;

/// The normal error a calibration with this covariance makes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Expected {
    /// RMS angle [deg] over draws and poses (the 1σ-equivalent).
    pub rms_deg: f64,
    /// 95th percentile [deg].
    pub p95_deg: f64,
    /// Resamples refitted.
    pub draws: usize,
    /// Poses whose plane all four beams meet.
    pub poses: usize,
}

/// Angle [deg] between two directions, sign-blind, accurate near 0.
fn line_angle(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b).abs()).to_degrees()
}

/// Expected normal error of the head `fitted` (four sensors) over the
/// poses of `run`, by `draws` seeded pose resamples, each refitted with
/// `refit`.
///
/// # Errors
/// Not four sensors, no pose with a plane all four beams meet, or no
/// resample that could be refitted.
pub fn expected_normal_error(
    fitted: &[Sensor<f64>],
    run: &PoseTable,
    refit: &dyn Fn(&Subset<'_>) -> Option<Vec<Sensor<f64>>>,
    draws: usize,
    seed: u64,
) -> Result<Expected> {
    let four = |s: &[Sensor<f64>]| -> Result<Head4<f64>> {
        let a: [Sensor<f64>; 4] = s
            .to_vec()
            .try_into()
            .map_err(|_| anyhow!("the expected accuracy is computed for four-sensor heads"))?;
        Ok(Head4::new(a))
    };
    let head = four(fitted)?;
    let planes: Vec<Plane<f64>> = (0..run.len()).map(|k| run.plane(k)).collect();
    let readings: Vec<([Option<f64>; 4], &Plane<f64>)> = planes
        .iter()
        .filter_map(|p| {
            let r: [Option<f64>; 4] =
                core::array::from_fn(|i| distance(&head.sensors[i], p, i).ok());
            r.iter().all(Option::is_some).then_some((r, p))
        })
        .collect();
    if readings.is_empty() {
        bail!("no pose of the run has a plane all four beams meet");
    }
    let mut rng = StdRng::seed_from_u64(seed);
    let mut angles = Vec::with_capacity(draws * readings.len());
    let mut used = 0;
    for _ in 0..draws {
        let idx: Vec<usize> = (0..run.len())
            .map(|_| rng.gen_range(0..run.len()))
            .collect();
        let Some(h) = refit(&Subset {
            all: run,
            idx: &idx,
        })
        .and_then(|s| four(&s).ok()) else {
            continue;
        };
        used += 1;
        for (r, p) in &readings {
            // A draw so far off that the plane cannot be fitted counts as
            // a 90° error rather than vanishing from the statistic.
            let a = plane(&h, r, &Context::default(), Method::Chen)
                .map(|f| line_angle(&f.normal, &p.n))
                .unwrap_or(90.0);
            angles.push(a);
        }
    }
    if used == 0 {
        bail!("no resample of the run's poses could be refitted");
    }
    angles.sort_by(f64::total_cmp);
    let n = angles.len();
    let rms = (angles.iter().map(|a| a * a).sum::<f64>() / n as f64).sqrt();
    let p95 = angles[((0.95 * n as f64).ceil() as usize).clamp(1, n) - 1];
    Ok(Expected {
        rms_deg: rms,
        p95_deg: p95,
        draws: used,
        poses: readings.len(),
    })
}

/// The least-squares refit of the paper's model (no extension) on a
/// resample, starting from `nominal`: the `refit` of
/// [`expected_normal_error`] for a base calibration.
pub fn base_refit(
    nominal: &[Sensor<f64>],
) -> impl Fn(&Subset<'_>) -> Option<Vec<Sensor<f64>>> + '_ {
    move |sub: &Subset<'_>| {
        nominal
            .iter()
            .enumerate()
            .map(|(i, s)| {
                perpend_core::calib::fit_sensor_base(s, i, sub, &LsqConfig::default())
                    .ok()
                    .map(|f| f.sensor)
            })
            .collect()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::sim::{paper_head, simulate, SimConfig};

    #[test]
    fn noise_free_run_gives_zero_error_and_bad_inputs_are_errors() {
        let head = paper_head().unwrap();
        let mut cfg = SimConfig::paper();
        cfg.zeta_mm = 0.0;
        cfg.tracker = None;
        let mut rng = StdRng::seed_from_u64(3);
        let data = simulate(&head, &cfg, &[], &mut rng).unwrap();
        let refit = base_refit(&head.truth);
        let e = expected_normal_error(&head.truth, &data.poses, &refit, 8, 1).unwrap();
        assert!(e.rms_deg < 1e-6, "{e:?}");
        assert_eq!(e.draws, 8);
        assert!(expected_normal_error(&head.truth[..3], &data.poses, &refit, 8, 1).is_err());
        let never = |_: &Subset<'_>| None;
        assert!(expected_normal_error(&head.truth, &data.poses, &never, 8, 1).is_err());
    }
}

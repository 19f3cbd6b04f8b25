//! Step 2b of a cell run: the calibration from the captured poses
//! (`perpend calibrate`: least squares, the paper's model, into
//! `DIR/params.json`) and its expected normal error from its own
//! parameter uncertainty ([`perpend_calib::accuracy`]).

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context as _, Result};

/// What the calibration step leaves: the parameter file and its expected
/// normal error.
#[derive(Debug, Clone)]
pub struct Fit {
    /// `DIR/params.json` (with `params.record.json` beside it).
    pub params: PathBuf,
    /// Expected normal error [deg RMS] from the parameters' own
    /// uncertainty (no reading noise).
    pub expected_deg: f64,
    /// Its 95th percentile [deg].
    pub expected_p95_deg: f64,
}

/// Calibrates the captured `poses` from the nominal head `sensors` into
/// `DIR/params.json` and computes its expected error; a calibration whose
/// expected error already exceeds `tolerance_deg` cannot verify and stops
/// the run before anything is pushed.
///
/// # Errors
/// The calibration's, or the tolerance with what to check.
pub fn run(sensors: &Path, poses: &Path, out: &Path, tolerance_deg: f64) -> Result<Fit> {
    let params = out.join("params.json");
    calibrate(sensors, poses, &params)?;
    let (expected, expected_p95) = expected_deg(sensors, poses, &params)?;
    if expected > tolerance_deg {
        bail!(
            "the new calibration's expected normal error {expected:.4}° (from its own parameter \
             uncertainty, no reading noise) exceeds the tolerance {tolerance_deg}°: it cannot \
             verify and was not pushed; check the captures in {} (did the readings follow the \
             planes? is the plan's reach wide enough?)",
            poses.display()
        );
    }
    Ok(Fit {
        params,
        expected_deg: expected,
        expected_p95_deg: expected_p95,
    })
}

/// Calibrates `poses` from the nominal head into `params`.
fn calibrate(sensors: &Path, poses: &Path, params: &Path) -> Result<()> {
    use perpend_calib::calibrate as cal;
    cal::run(&cal::Args {
        sensors: sensors.to_path_buf(),
        poses: poses.to_path_buf(),
        method: cal::Method::Lsq,
        model: cal::Model::Base,
        out: Some(params.to_path_buf()),
        ekf_preset: cal::EkfPreset::Simulation,
        ekf_r: None,
        ekf_q: None,
        ekf_delta: None,
        ekf_nonlinear: false,
        ekf_joseph: false,
        keep_outliers: false,
    })
}

/// The calibration's expected normal error [deg RMS] over the captured
/// poses: the bootstrap of `perpend calibrate` ([`perpend_calib::accuracy`],
/// the paper's model refitted from the nominal head).
fn expected_deg(sensors: &Path, poses: &Path, params: &Path) -> Result<(f64, f64)> {
    use perpend_calib::accuracy::{base_refit, expected_normal_error};
    let nominal = perpend_formats::exchange::read_sensors(sensors)?
        .sensors()
        .map_err(|e| anyhow!("{}: {e}", sensors.display()))?;
    let table = perpend_formats::exchange::read_poses(poses, Some(nominal.len()))?;
    let fitted = perpend_formats::paramfile::ParamFile::read(params)?.sensors()?;
    let e = expected_normal_error(&fitted, &table, &base_refit(&nominal), 100, 1)
        .context("the calibration's expected normal error")?;
    Ok((e.rms_deg, e.p95_deg))
}

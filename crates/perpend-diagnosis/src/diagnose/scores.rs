//! Stage 6 of `perpend diagnose`, held-out scores of the verdict: the
//! paper's model's and the named model's held-out residual RMS and
//! held-out normal errors ([`perpend_calib::cv::normal_errors`]), what the report
//! states as the gain.
//!
//! Input: the verdict (the effect and the forward selection's steps), the
//! measured [`Analysis`] and the loaded run; output: `Scores`. Reads
//! stages 0-5 only; refits nothing (the steps carry their
//! cross-validation). Limits: a pose without three readings has no normal
//! error; the mean skips it.

use serde::{Deserialize, Serialize};

use super::decision::Step;
use super::expect::Analysis;
use super::load::Loaded;
use super::settings::Settings;
use perpend_calib::candidates::Effect;
use perpend_calib::cv::normal_errors;
use perpend_calib::stats;

/// Held-out performance of a model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Perf {
    /// Held-out residual RMS [mm].
    pub heldout_rms_mm: f64,
    /// Mean held-out normal error [deg] (`null` when no pose's normal could
    /// be measured).
    pub heldout_normal_err_deg: Option<f64>,
}

/// Held-out performance of the paper's model and of the model behind the
/// verdict (stage "held-out scores" of what is reported).
#[derive(Debug, Clone)]
pub struct Scores {
    /// The paper's model's held-out performance.
    pub base: Perf,
    /// The named model's (= `base` for `none` and `unexplained`).
    pub extended: Perf,
    /// Held-out normal error per pose, paper's model [deg].
    pub base_normals: Vec<Option<f64>>,
    /// Held-out normal error per pose, named model [deg].
    pub ext_normals: Vec<Option<f64>>,
    /// The model behind `extended` (`None` = the paper's).
    pub ext_model: Effect,
}

/// [`Scores`] of the verdict `effect` (with the forward selection's
/// `also`): the extended figures are those of the last model selected,
/// the paper's model's for `none` and `unexplained`.
pub(super) fn scores(
    effect: Effect,
    also: &[Step],
    measured: &Analysis,
    l: &Loaded,
    s: &Settings,
) -> Scores {
    let base_normals = measured.base_normal.clone();
    let base = Perf {
        heldout_rms_mm: measured.cv_of(Effect::None).map_or(f64::NAN, |c| c.rms),
        heldout_normal_err_deg: mean_opt(&base_normals),
    };
    let ext_model = match effect {
        Effect::None | Effect::Unexplained => Effect::None,
        e => e,
    };
    let ext_cv = also.last().map(|st| &st.cv).or(measured.cv_of(ext_model));
    let (extended, ext_normals) = match ext_cv {
        Some(c) if ext_model != Effect::None => {
            let ne = normal_errors(c, &l.poses, &l.folds, s.method);
            let perf = Perf {
                heldout_rms_mm: c.rms,
                heldout_normal_err_deg: mean_opt(&ne),
            };
            (perf, ne)
        }
        _ => (base, base_normals.clone()),
    };
    Scores {
        base,
        extended,
        base_normals,
        ext_normals,
        ext_model,
    }
}

fn mean_opt(v: &[Option<f64>]) -> Option<f64> {
    let x: Vec<f64> = v.iter().flatten().copied().collect();
    (!x.is_empty()).then(|| stats::mean(&x))
}

//! Stages 2 and 3 of `perpend diagnose`, nominal fit and candidate fits:
//! the paper's model and every candidate the run allows, each
//! cross-validated by pose on the measured run ([`super::expect::analyse`],
//! [`perpend_calib::cv`]), and the candidates whose fit on all poses leaves the
//! physical bounds ([`perpend_calib::candidates::plausible`]).
//!
//! Input: the [`Plan`] of the loaded run; output: the measured
//! [`Analysis`], the models fitted and those that failed. Reads stage 1
//! ([`super::load`]) only. Limits: a paper's model that cannot be
//! cross-validated ends the diagnosis.

use anyhow::{anyhow, bail, Result};
use perpend_core::calib::LsqConfig;
use perpend_core::head::Sensor;

use super::expect::{analyse, Analysis, Plan};
use super::load::{reading_span, Loaded, Skipped};
use super::settings::Settings;
use perpend_calib::candidates::{self, Effect, Refs};
use perpend_formats::exchange::PoseTable;

/// Stage "nominal fit → candidates": every model cross-validated on the
/// measured run ([`analyse`]); returns the analysis, the models that could
/// be fitted, and those that could not with why.
///
/// # Errors
/// The paper's model cannot be cross-validated.
fn fit_measured(poses: &PoseTable, plan: &Plan) -> Result<(Analysis, Vec<Effect>, Skipped)> {
    let measured = analyse(poses, plan, true).map_err(|e| anyhow!("{e}"))?;
    match measured.cv.first() {
        Some((_, Ok(_))) => {}
        Some((_, Err(e))) => bail!("the paper's model cannot be cross-validated: {e}"),
        None => bail!("no model"),
    }
    let mut fitted = Vec::new();
    let mut failed = Vec::new();
    for (e, r) in &measured.cv {
        match r {
            Ok(_) => fitted.push(*e),
            Err(why) => failed.push((*e, format!("cannot be fitted: {why}"))),
        }
    }
    Ok((measured, fitted, failed))
}

/// Candidates whose fit on all poses leaves the physical bounds.
pub(super) fn implausible_fits(
    nominal: &[Sensor<f64>],
    poses: &PoseTable,
    refs: &Refs,
    models: &[Effect],
    lsq: &LsqConfig<f64>,
) -> Vec<(Effect, String)> {
    let span = reading_span(poses, refs);
    models
        .iter()
        .filter(|e| **e != Effect::None)
        .filter_map(|&e| {
            let fits = candidates::fit_all(nominal, poses, refs, e, lsq).ok()?;
            candidates::plausible(e, &fits, span)
                .err()
                .map(|why| (e, why))
        })
        .collect()
}

/// The output of stages 2-3: the measured run's analysis and which models
/// it could fit.
#[derive(Debug, Clone)]
pub struct Fitted {
    /// Every model cross-validated on the measured run.
    pub measured: Analysis,
    /// The models fitted (the paper's first); the later stages simulate
    /// and decide among these only.
    pub fitted: Vec<Effect>,
    /// Models that could not be fitted, with why.
    pub failed: Skipped,
    /// Fitted models whose fit on all poses leaves the physical bounds.
    pub implausible: Vec<(Effect, String)>,
}

/// Stages 2-3 on the loaded run `l` ([`fit_measured`], [`implausible_fits`]).
///
/// # Errors
/// Those of [`fit_measured`].
pub(super) fn fit(l: &Loaded, s: &Settings) -> Result<Fitted> {
    let (measured, fitted, failed) = fit_measured(&l.poses, &l.plan(&l.models, s))?;
    let implausible = implausible_fits(&l.nominal, &l.poses, &l.refs, &fitted, &s.lsq);
    Ok(Fitted {
        measured,
        fitted,
        failed,
        implausible,
    })
}

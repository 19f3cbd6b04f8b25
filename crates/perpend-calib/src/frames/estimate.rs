//! Joint estimation of the head and the frame errors, and the
//! identifiability of the frame errors (see the [`super`] header for the
//! model and the reversal principle).
//!
//! Gauss-Newton on `r = d_meas − d(head, true_plane(pose, frames))`, the
//! head's columns from Chen eq. 7-9 in the 5-DOF form, the frames' by
//! central differences; each step solves the column-scaled system by SVD,
//! dropping singular values below `1e-7·σ_max` (a minimum-norm step: what
//! the readings cannot see is left at its start value). The covariance is
//! `s²·(JᵀJ)⁺` with `s² = RSS / (m − rank)`.
//!
//! Every frame error outside the Jacobian's null space is estimated and
//! reported with its 1σ, however large (issue 46): precision decides only
//! what is called resolved and what the handed-over head is corrected for
//! ([`estimate`]), never whether a value is given. Limits: the 1σ is the
//! linearised one at the fit, with `s` from the residual (white reading
//! noise; a tracker's per-pose plane error is not separated from it).

use anyhow::{anyhow, bail, Result};
use nalgebra::{DMatrix, DVector};
use perpend_core::head::{Sensor, DOF};
use perpend_core::model::{distance, jacobian};
use serde::Serialize;

use super::{
    is_angle, is_significant, true_plane, FramePose, Frames, Tolerance, CORRECT_Z, FRAME_NAMES,
    NULL_SHARE, N_FRAME, RANK_TOL,
};

/// Gauss-Newton iterations at most.
const MAX_ITER: usize = 12;
/// Step (scaled units) below which the iteration has converged.
const STEP_TOL: f64 = 1e-9;

/// The linearised problem at one point.
struct Design {
    /// Jacobian with columns scaled to physical units.
    js: DMatrix<f64>,
    /// Residuals [mm].
    r: DVector<f64>,
    /// Column scales (parameter = scale · scaled parameter).
    scale: DVector<f64>,
}

/// The SVD solution of a [`Design`].
struct Solved {
    rank: usize,
    condition: f64,
    /// Gauss-Newton step in parameter units.
    step: DVector<f64>,
    /// `diag((JᵀJ)⁺)` in parameter units (times s² = variance).
    cov_diag: DVector<f64>,
    /// Share of each parameter in the numerical null space.
    null_share: DVector<f64>,
}

/// What the readings can tell of one frame error.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FrameIdent {
    /// Which frame error.
    pub name: &'static str,
    /// Share of its unit vector in the Jacobian's null space (1 = not
    /// identifiable at all, absorbed by the head).
    pub null_share: f64,
    /// 1σ [rad or mm] of its estimate if it were estimated (`None` when in
    /// the null space).
    pub sigma: Option<f64>,
    /// Identifiable and 1σ within [`Tolerance::fallback`] (a description
    /// of the precision with these poses; the estimate's own `resolved` is
    /// judged against the calibration's expected error, [`estimate`]).
    pub resolved: bool,
}

/// Identifiability of the frame errors with a set of poses.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Ident {
    /// Parameters (5 per sensor + 6 frame errors).
    pub params: usize,
    /// Numerical rank of the scaled Jacobian.
    pub rank: usize,
    /// Condition number of its identifiable part (σ_max / smallest kept σ).
    pub condition: f64,
    /// Per frame error, in [`FRAME_NAMES`] order.
    pub frames: Vec<FrameIdent>,
}

/// The joint fit.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameFit {
    /// The head handed over (in the true TCS): fitted together with the
    /// frame errors of `corrected`, the others held at 0.
    pub head: Vec<Sensor<f64>>,
    /// Estimated frame errors: every identifiable one, whatever its
    /// precision (0 where not identifiable, or in a head-only fit).
    pub frames: Frames,
    /// 1σ of each estimate (`None`: not identifiable, or not estimated).
    pub sigma: [Option<f64>; N_FRAME],
    /// Estimated and 1σ within `tolerance`.
    pub resolved: [bool; N_FRAME],
    /// Estimated and beyond [`super::SIGNIFICANT_Z`]·1σ.
    pub significant: [bool; N_FRAME],
    /// Whether `head` is corrected for it (resolved, or beyond
    /// [`super::CORRECT_Z`]·1σ).
    pub corrected: [bool; N_FRAME],
    /// The frame errors `head` was fitted with (0 where not corrected): the
    /// correction of the tracker's planes that goes with `head`.
    pub correction: Frames,
    /// The precision that counts as resolved.
    pub tolerance: Tolerance,
    /// Identifiability of all six with these poses (1σ scaled by `s`).
    pub ident: Ident,
    /// Residual RMS [mm] of the fit with every identifiable frame error.
    pub rms_mm: f64,
    /// `s` [mm]: its residual scale, `sqrt(RSS / (m − rank))`.
    pub s_mm: f64,
}

/// Mean radius [mm] of the zero points about the spindle axis (the lever
/// that turns angles into millimetres for the column scaling).
fn radius(head: &[Sensor<f64>]) -> f64 {
    let r = head.iter().map(|s| s.zero.xy().norm()).sum::<f64>() / head.len().max(1) as f64;
    if r > 1.0 {
        r
    } else {
        50.0
    }
}

/// Column scale of frame error `j`.
fn frame_scale(j: usize, r: f64) -> f64 {
    if is_angle(j) {
        1.0 / r
    } else {
        1.0
    }
}

/// Central-difference derivative of sensor `i`'s distance at `pose` by
/// frame error `j`.
fn frame_column(s: &Sensor<f64>, i: usize, pose: &FramePose, f: &Frames, j: usize) -> Result<f64> {
    let h = if is_angle(j) { 1e-6 } else { 1e-4 };
    let mut fp = *f;
    fp[j] += h;
    let mut fm = *f;
    fm[j] -= h;
    let dp = distance(s, &true_plane(pose, &fp), i)?;
    let dm = distance(s, &true_plane(pose, &fm), i)?;
    Ok((dp - dm) / (2.0 * h))
}

/// The design at `head`, `f`, with the frame errors `free` as columns.
fn design(
    head: &[Sensor<f64>],
    f: &Frames,
    free: &[usize],
    poses: &[FramePose],
    readings: &[Vec<Option<f64>>],
) -> Result<Design> {
    let ns = head.len();
    let cols = DOF * ns + free.len();
    let r0 = radius(head);
    let mut rows: Vec<f64> = Vec::new();
    let mut res: Vec<f64> = Vec::new();
    for (k, (pose, row)) in poses.iter().zip(readings).enumerate() {
        let q = true_plane(pose, f);
        for (i, s) in head.iter().enumerate() {
            let Some(meas) = row.get(i).copied().flatten() else {
                continue;
            };
            let (d, g) = jacobian(s, &q, i).map_err(|e| anyhow!("pose {}: {e}", k + 1))?;
            let mut line = vec![0.0; cols];
            line[DOF * i..DOF * (i + 1)].copy_from_slice(g.as_slice());
            for (c, &j) in free.iter().enumerate() {
                line[DOF * ns + c] = frame_column(s, i, pose, f, j)?;
            }
            rows.extend(line);
            res.push(meas - d);
        }
    }
    let scale = DVector::from_fn(cols, |c, _| {
        if c < DOF * ns {
            if c % DOF < 3 {
                1.0
            } else {
                1.0 / r0
            }
        } else {
            frame_scale(free[c - DOF * ns], r0)
        }
    });
    let mut js = DMatrix::from_row_slice(res.len(), cols, &rows);
    for (c, mut col) in js.column_iter_mut().enumerate() {
        col *= scale[c];
    }
    Ok(Design {
        js,
        r: DVector::from_vec(res),
        scale,
    })
}

/// Truncated-SVD solution of `d`.
fn solve(d: &Design) -> Result<Solved> {
    let n = d.js.ncols();
    if d.js.nrows() <= n {
        bail!(
            "{} readings for {n} parameters: take more poses (at least {} readings)",
            d.js.nrows(),
            n + 1
        );
    }
    let svd = d.js.clone().svd(true, true);
    let v_t = svd.v_t.as_ref().ok_or_else(|| anyhow!("SVD without V"))?;
    let u = svd.u.as_ref().ok_or_else(|| anyhow!("SVD without U"))?;
    let smax = svd.singular_values.max();
    let tol = RANK_TOL * smax;
    let mut step = DVector::zeros(n);
    let mut cov = DVector::zeros(n);
    let mut null = DVector::zeros(n);
    let (mut rank, mut smin) = (0, smax);
    for (i, &sv) in svd.singular_values.iter().enumerate() {
        let v = v_t.row(i).transpose();
        if sv > tol {
            rank += 1;
            smin = smin.min(sv);
            step += &v * (u.column(i).dot(&d.r) / sv);
            cov += v.map(|x| x * x / (sv * sv));
        } else {
            null += v.map(|x| x * x);
        }
    }
    Ok(Solved {
        rank,
        condition: smax / smin,
        step: step.component_mul(&d.scale),
        cov_diag: cov.component_mul(&d.scale.map(|x| x * x)),
        null_share: null.map(f64::sqrt),
    })
}

/// Applies a step to the head and the free frame errors.
fn apply(
    head: &mut [Sensor<f64>],
    f: &mut Frames,
    free: &[usize],
    step: &DVector<f64>,
) -> Result<()> {
    for (i, s) in head.iter_mut().enumerate() {
        let d = nalgebra::SVector::<f64, DOF>::from_fn(|k, _| step[DOF * i + k]);
        *s = s
            .retract(&d)
            .map_err(|e| anyhow!("sensor {}: {e}", i + 1))?;
    }
    let ns = head.len();
    for (c, &j) in free.iter().enumerate() {
        f[j] += step[DOF * ns + c];
    }
    Ok(())
}

/// Gauss-Newton from `head`, `f` with the frame errors `free`; returns the
/// last solution (at the converged point) and the RMS.
fn gauss_newton(
    head: &mut [Sensor<f64>],
    f: &mut Frames,
    free: &[usize],
    poses: &[FramePose],
    readings: &[Vec<Option<f64>>],
) -> Result<(Solved, Design)> {
    for _ in 0..MAX_ITER {
        let d = design(head, f, free, poses, readings)?;
        let s = solve(&d)?;
        let small = s.step.component_div(&d.scale).amax() < STEP_TOL;
        apply(head, f, free, &s.step)?;
        if small {
            break;
        }
    }
    let d = design(head, f, free, poses, readings)?;
    let s = solve(&d)?;
    Ok((s, d))
}

/// Residual scale `s` [mm] and RMS [mm] of a solved design.
fn scale_of(s: &Solved, d: &Design) -> (f64, f64) {
    let m = d.r.len();
    let rss = d.r.norm_squared();
    let dof = m.saturating_sub(s.rank).max(1);
    ((rss / dof as f64).sqrt(), (rss / m.max(1) as f64).sqrt())
}

/// Identifiability of all six frame errors together with the head at
/// `head`, `f`, the 1σ scaled by the residual scale `s_mm`.
///
/// # Errors
/// Beams that miss a plane, fewer readings than parameters.
pub fn identify(
    head: &[Sensor<f64>],
    f: &Frames,
    poses: &[FramePose],
    readings: &[Vec<Option<f64>>],
    s_mm: f64,
) -> Result<Ident> {
    let all: Vec<usize> = (0..N_FRAME).collect();
    let d = design(head, f, &all, poses, readings)?;
    let s = solve(&d)?;
    let base = DOF * head.len();
    let frames = (0..N_FRAME)
        .map(|j| {
            let null_share = s.null_share[base + j];
            let sigma = (null_share < NULL_SHARE).then(|| s_mm * s.cov_diag[base + j].sqrt());
            FrameIdent {
                name: FRAME_NAMES[j],
                null_share,
                sigma,
                resolved: sigma.is_some_and(|x| Tolerance::fallback().resolves(j, x)),
            }
        })
        .collect();
    Ok(Ident {
        params: d.js.ncols(),
        rank: s.rank,
        condition: s.condition,
        frames,
    })
}

/// One Gauss-Newton fit from `start` with the frame errors `free`.
struct Fitted {
    head: Vec<Sensor<f64>>,
    f: Frames,
    /// 1σ of each free frame error, `s·sqrt(diag (JᵀJ)⁺)`.
    sigma: [Option<f64>; N_FRAME],
    s_mm: f64,
    rms_mm: f64,
}

fn fit_from(
    start: &(Vec<Sensor<f64>>, Frames),
    free: &[usize],
    poses: &[FramePose],
    readings: &[Vec<Option<f64>>],
) -> Result<Fitted> {
    let (mut head, mut f) = start.clone();
    let (sol, d) = gauss_newton(&mut head, &mut f, free, poses, readings)?;
    let (s_mm, rms_mm) = scale_of(&sol, &d);
    let mut sigma = [None; N_FRAME];
    for (c, &j) in free.iter().enumerate() {
        sigma[j] = Some(s_mm * sol.cov_diag[DOF * head.len() + c].sqrt());
    }
    Ok(Fitted {
        head,
        f,
        sigma,
        s_mm,
        rms_mm,
    })
}

/// Calibrates the head alone (`joint` = `None`: the usual calibration, the
/// frame errors absorbed), or the head and every frame error the poses can
/// identify (not in the Jacobian's null space, [`identify`] at the
/// head-only fit), whatever its precision.
///
/// Every identifiable frame error is estimated with its 1σ, called
/// significant beyond [`super::SIGNIFICANT_Z`]·1σ and resolved when its 1σ is
/// within `joint`'s [`Tolerance`]. The head handed over ([`FrameFit::head`])
/// is corrected for those that are resolved or beyond
/// [`super::CORRECT_Z`]·1σ; any other (an unresolved estimate within 3σ of
/// 0, e.g. a tracker tilt without reversal, 1σ ≈ 0.05°) is held at 0
/// there, since correcting it would add its 1σ to every normal to remove
/// little more.
///
/// # Errors
/// Beams that miss a plane, fewer readings than parameters.
pub fn estimate(
    nominal: &[Sensor<f64>],
    poses: &[FramePose],
    readings: &[Vec<Option<f64>>],
    joint: Option<Tolerance>,
) -> Result<FrameFit> {
    if poses.len() != readings.len() {
        bail!(
            "{} poses but {} rows of readings",
            poses.len(),
            readings.len()
        );
    }
    let start = (nominal.to_vec(), Frames::zeros());
    let plain = fit_from(&start, &[], poses, readings)?;
    let ident = identify(&plain.head, &plain.f, poses, readings, plain.s_mm)?;
    let Some(tol) = joint else {
        return Ok(FrameFit::head_only(plain, ident));
    };
    let start = (plain.head.clone(), plain.f);
    let free: Vec<usize> = (0..N_FRAME)
        .filter(|&j| ident.frames[j].sigma.is_some())
        .collect();
    let full = fit_from(&start, &free, poses, readings)?;
    let ident = identify(&full.head, &full.f, poses, readings, full.s_mm)?;
    let resolved: [bool; N_FRAME] =
        core::array::from_fn(|j| full.sigma[j].is_some_and(|s| tol.resolves(j, s)));
    let significant: [bool; N_FRAME] =
        core::array::from_fn(|j| full.sigma[j].is_some_and(|s| is_significant(full.f[j], s)));
    let corrected: [bool; N_FRAME] = core::array::from_fn(|j| {
        resolved[j] || full.sigma[j].is_some_and(|s| full.f[j].abs() > CORRECT_Z * s)
    });
    let keep: Vec<usize> = free.iter().copied().filter(|&j| corrected[j]).collect();
    let (head, correction) = if keep.len() == free.len() {
        (full.head, full.f)
    } else if keep.is_empty() {
        start
    } else {
        let c = fit_from(&start, &keep, poses, readings)?;
        (c.head, c.f)
    };
    Ok(FrameFit {
        head,
        frames: full.f,
        sigma: full.sigma,
        resolved,
        significant,
        corrected,
        correction,
        tolerance: tol,
        ident,
        rms_mm: full.rms_mm,
        s_mm: full.s_mm,
    })
}

impl FrameFit {
    /// The head-only calibration as a [`FrameFit`] (nothing estimated,
    /// nothing corrected).
    fn head_only(plain: Fitted, ident: Ident) -> Self {
        Self {
            head: plain.head,
            frames: Frames::zeros(),
            sigma: [None; N_FRAME],
            resolved: [false; N_FRAME],
            significant: [false; N_FRAME],
            corrected: [false; N_FRAME],
            correction: Frames::zeros(),
            tolerance: Tolerance::fallback(),
            ident,
            rms_mm: plain.rms_mm,
            s_mm: plain.s_mm,
        }
    }
}

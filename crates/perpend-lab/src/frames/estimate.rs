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

use anyhow::{anyhow, bail, Result};
use nalgebra::{DMatrix, DVector};
use perpend_core::head::{Sensor, DOF};
use perpend_core::model::{distance, jacobian};
use serde::Serialize;

use super::{
    is_angle, true_plane, FramePose, Frames, FRAME_NAMES, NULL_SHARE, N_FRAME, RANK_TOL,
    RESOLVE_MM, RESOLVE_RAD,
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
    /// Identifiable and 1σ within [`RESOLVE_RAD`] / [`RESOLVE_MM`].
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
    /// The estimated head (in the true TCS).
    pub head: Vec<Sensor<f64>>,
    /// Estimated frame errors (0 where not estimated).
    pub frames: Frames,
    /// 1σ of each estimated frame error (`None` where not estimated).
    pub sigma: [Option<f64>; N_FRAME],
    /// Identifiability of all six with these poses (1σ scaled by `s`).
    pub ident: Ident,
    /// Residual RMS [mm].
    pub rms_mm: f64,
    /// `s` [mm]: residual scale, `sqrt(RSS / (m − rank))`.
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
            let limit = if is_angle(j) { RESOLVE_RAD } else { RESOLVE_MM };
            FrameIdent {
                name: FRAME_NAMES[j],
                null_share,
                sigma,
                resolved: sigma.is_some_and(|x| x <= limit),
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

/// Calibrates the head alone (`frames` = false: the usual calibration, the
/// frame errors absorbed) or the head and every frame error the poses
/// resolve ([`identify`] at the head-only fit decides which).
///
/// # Errors
/// Beams that miss a plane, fewer readings than parameters.
pub fn estimate(
    nominal: &[Sensor<f64>],
    poses: &[FramePose],
    readings: &[Vec<Option<f64>>],
    frames: bool,
) -> Result<FrameFit> {
    if poses.len() != readings.len() {
        bail!(
            "{} poses but {} rows of readings",
            poses.len(),
            readings.len()
        );
    }
    let mut head = nominal.to_vec();
    let mut f = Frames::zeros();
    let (s0, d0) = gauss_newton(&mut head, &mut f, &[], poses, readings)?;
    let (s_head, _) = scale_of(&s0, &d0);
    let pre = identify(&head, &f, poses, readings, s_head)?;
    // First every frame error the poses can see at all, then only those
    // whose 1σ (with the joint fit's own residual) resolves them.
    let mut free: Vec<usize> = if frames {
        (0..N_FRAME)
            .filter(|&j| pre.frames[j].sigma.is_some())
            .collect()
    } else {
        Vec::new()
    };
    let start = (head.clone(), f);
    loop {
        (head, f) = start.clone();
        let (sol, d) = gauss_newton(&mut head, &mut f, &free, poses, readings)?;
        let (s_mm, rms_mm) = scale_of(&sol, &d);
        let ident = identify(&head, &f, poses, readings, s_mm)?;
        let kept: Vec<usize> = free
            .iter()
            .copied()
            .filter(|&j| ident.frames[j].resolved)
            .collect();
        if kept.len() < free.len() {
            free = kept;
            continue;
        }
        let mut sigma = [None; N_FRAME];
        for (c, &j) in free.iter().enumerate() {
            sigma[j] = Some(s_mm * sol.cov_diag[DOF * head.len() + c].sqrt());
        }
        return Ok(FrameFit {
            head,
            frames: f,
            sigma,
            ident,
            rms_mm,
            s_mm,
        });
    }
}

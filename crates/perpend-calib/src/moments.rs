//! Reading and datum-plane noise by the method of moments, through the
//! fitted model's own residual operator.
//!
//! Noise enters a pose's readings in two ways ([`crate::noise`]): reading
//! noise `ε`, independent between sensors, and the datum-plane error of
//! the tracker, which moves the readings of a pose together along the
//! plane columns `A_k` (Chen eq. 3 differentiated). The fit then removes
//! part of both: the in-sample residual is `r = R·(ε + e)`, with `R = I −
//! J·J⁺` the residual operator of each sensor's fit (`J` the Jacobian of
//! its prediction over the poses: five geometry values and the extension
//! coefficients). Split per pose into the part inside the plane columns
//! (`I`) and outside (`W`), the expected energies are linear in the two
//! unknowns, the reading variance σ² and the tracker's variance scale `s`
//! (ξ = ξ₀·√s):
//!
//! ```text
//! E[W] = σ²·U₁ + s·U₂      E[I] = σ²·T₁ + s·T₂
//! ```
//!
//! `U₁`, `T₁` are exact: unit reading noise on each reading in turn,
//! entering its own residual whole and, through terms that read another
//! channel (the carry-over), the predictions of the pose's other sensors
//! with their coefficient, each sensor's part pushed through its `R`
//! (`tr(MᵀPM)`; without such terms it reduces to `Σ R_oo·(1 − h_o)` and
//! `Σ R_oo·h_o`, `h_o` the leverage of reading `o` in its pose's plane
//! columns). `U₂`, `T₂` are averaged over draws of the nominal tracker on
//! the run's planes, their change to each fitted prediction (extension
//! terms included) pushed through `R`, no refit.
//! Two equations, two unknowns. This replaces a ratio of plane energies
//! between the measured run (full model) and simulated runs (paper's
//! model): the full model's terms that read another channel (crosstalk)
//! absorb part of a pose's plane error, which that ratio counted as
//! missing and so put ξ about 8 % low at a tracker 3× the nominal.
//! Refitting the full model on simulated runs instead was tried and is
//! unstable (its crosstalk coefficient is weakly identified, ±2 on
//! effect-free draws, and the share it absorbs varies by 10×); the
//! linearised operator is what the fit on the measured run actually did.
//!
//! Limits: linear in the noise (the fit's Jacobian at its solution, fine
//! while the noise is small against the pose spread); σ is pooled over
//! sensors; the tracker's shape (offset against tilt error) is the nominal
//! model's, only its scale is estimated, and `U₂`, `T₂` carry the Monte
//! Carlo error of [`DRAWS`] draws (a few % of the plane energy); a plane
//! part within two standard errors of what reading noise alone gives it is
//! flagged as not resolved (and kept), a negative one is none (σ² then
//! from `W` alone); poses with fewer than four readings carry
//! no within-pose part and are left out of both energies, and without any
//! such pose there is nothing to solve. Each sensor's `R` is a dense
//! `K × K` matrix and the reading part costs `O(K²)` per sensor (about
//! 36 ms at 500 poses, release build).

use nalgebra::DMatrix;
use perpend_core::calib::Poses;
use perpend_core::geometry::tangent_basis;
use perpend_core::geometry::Plane;
use perpend_core::head::Sensor;
use perpend_core::model::distance;
use rand::SeedableRng;

use crate::candidates::{predict, SensorFit};
use crate::sim::Tracker;
use perpend_formats::exchange::PoseTable;

/// The three plane-error columns of the sensors `idx` of a pose.
pub(super) fn plane_columns(
    sensors: &[Sensor<f64>],
    poses: &PoseTable,
    k: usize,
    idx: &[usize],
) -> Option<Vec<[f64; 3]>> {
    let plane = poses.plane(k);
    idx.iter()
        .map(|&i| {
            let s = sensors.get(i)?;
            let d = distance(s, &plane, i).ok()?;
            let p = s.spot(d);
            let c = plane.n.dot(&s.dir);
            (c.abs() > 1e-6).then(|| [1.0 / c, p.x / c, p.y / c])
        })
        .collect()
}

/// Orthonormal basis of the span of the columns `a` (Gram-Schmidt;
/// columns that are numerically dependent are dropped), each basis vector
/// over the rows of `a`.
pub(super) fn orthonormal(a: &[[f64; 3]]) -> Vec<Vec<f64>> {
    let mut basis: Vec<Vec<f64>> = Vec::new();
    for j in 0..3 {
        let mut v: Vec<f64> = a.iter().map(|row| row[j]).collect();
        for b in &basis {
            let dot: f64 = v.iter().zip(b).map(|(x, y)| x * y).sum();
            v.iter_mut().zip(b).for_each(|(x, y)| *x -= dot * y);
        }
        let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if norm > 1e-9 {
            basis.push(v.iter().map(|x| x / norm).collect());
        }
    }
    basis
}

/// Tracker draws behind `U₂`, `T₂`.
const DRAWS: u64 = 64;

/// The moment equations of a run and its fitted model.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Moments {
    /// Measured energy outside the plane columns [mm²].
    pub w: f64,
    /// Measured energy inside the plane columns [mm²].
    pub i: f64,
    /// `E[W]` per unit reading variance.
    pub u1: f64,
    /// `E[W]` per unit tracker scale.
    pub u2: f64,
    /// `E[I]` per unit reading variance.
    pub t1: f64,
    /// `E[I]` per unit tracker scale.
    pub t2: f64,
    /// Mean squared plane error at the spots per unit scale, before the
    /// fit [mm²].
    pub spot: f64,
}

/// What the moment equations give.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Solution {
    /// Reading variance σ² [mm²].
    pub var: f64,
    /// Tracker variance scale `s` (ξ = ξ₀·√s), 0 for none.
    pub scale: f64,
    /// Whether `s` is beyond two standard errors of reading noise alone.
    pub resolved: bool,
}

impl Moments {
    /// `σ²` and `s` solving both equations (`s` at least 0; with `σ²`
    /// below 0 by chance, `σ²` = 0 and the inside energy all plane error),
    /// and whether the plane part is resolved: `s·T₂` beyond two standard
    /// errors of what reading noise alone gives it. Its estimate is
    /// `I − (T₁/U₁)·W` (to first order), and with `I`, `W` scattering as
    /// χ² with `T₁`, `U₁` degrees of freedom that standard error is
    /// `σ²·√(2·(T₁ + T₁²/U₁))`. An unresolved positive `s` is kept: it is
    /// the estimate, and dropping it would make every null too narrow
    /// where the tracker is real but near the reading noise. `None`
    /// without within-pose equations (`U₁ = 0`: fewer than four readings
    /// in every pose).
    pub fn solve(&self) -> Option<Solution> {
        if !(self.u1 > 0.0) {
            return None;
        }
        let alone = Solution {
            var: self.w / self.u1,
            scale: 0.0,
            resolved: false,
        };
        let det = self.u1 * self.t2 - self.u2 * self.t1;
        if !(det.abs() >= 1e-12 * (self.u1 * self.t2).abs()) || !(self.t2 > 0.0) {
            return Some(alone);
        }
        let s = (self.u1 * self.i - self.t1 * self.w) / det;
        if !(s > 0.0) {
            return Some(alone);
        }
        let var = ((self.w * self.t2 - self.u2 * self.i) / det).max(0.0);
        let scale = if var > 0.0 { s } else { self.i / self.t2 };
        let se = var * (2.0 * (self.t1 + self.t1 * self.t1 / self.u1)).sqrt();
        Some(Solution {
            var,
            scale,
            resolved: scale * self.t2 > 2.0 * se,
        })
    }

    /// `σ²` when the tracker scale is known (`s` in units of the tracker
    /// the moments were taken with).
    /// `None` without within-pose equations.
    pub fn var_given(&self, s: f64) -> Option<f64> {
        (self.u1 > 0.0).then(|| ((self.w - s * self.u2) / self.u1).max(0.0))
    }
}

/// One sensor's residual operator `I − J·J⁺` over the poses it read.
struct Operator {
    /// Pose index of each row.
    rows: Vec<usize>,
    /// The operator (rows × rows).
    r: DMatrix<f64>,
}

/// Jacobian columns of `fit`'s prediction in pose `k`: zero point (3),
/// direction (2, in its tangent plane: a unit vector has two degrees of
/// freedom), extension coefficients (their regressors). One working copy
/// of the fit is perturbed and restored for every column.
fn jacobian_row(fit: &SensorFit, poses: &PoseTable, k: usize, idx: usize) -> Option<Vec<f64>> {
    const H_ZERO: f64 = 1e-4;
    const H_DIR: f64 = 1e-6;
    let s = fit.sensor;
    let mut w = fit.clone();
    let mut row = Vec::with_capacity(5 + fit.coeffs.len());
    let mut diff = |a: Sensor<f64>, b: Sensor<f64>, h: f64| -> Option<f64> {
        w.sensor = a;
        let pa = predict(&w, poses, k, idx);
        w.sensor = b;
        let pb = predict(&w, poses, k, idx);
        w.sensor = s;
        Some((pa? - pb?) / (2.0 * h))
    };
    for axis in 0..3 {
        let (mut a, mut b) = (s, s);
        a.zero[axis] += H_ZERO;
        b.zero[axis] -= H_ZERO;
        row.push(diff(a, b, H_ZERO)?);
    }
    let (e1, e2) = tangent_basis(&s.dir);
    for e in [e1, e2] {
        let (mut a, mut b) = (s, s);
        a.dir = (s.dir + e * H_DIR).normalize();
        b.dir = (s.dir - e * H_DIR).normalize();
        row.push(diff(a, b, H_DIR)?);
    }
    let base = predict(fit, poses, k, idx)?;
    let mut w = fit.clone();
    for j in 0..fit.coeffs.len() {
        w.coeffs[j] += 1.0;
        let p = predict(&w, poses, k, idx);
        w.coeffs[j] = fit.coeffs[j];
        row.push(p? - base);
    }
    Some(row)
}

/// The residual operator of sensor `idx`'s fit over the poses where it
/// has a residual: a dense `K × K` matrix (poses read). Columns are scaled
/// to unit norm and singular values below `1e-9` of the largest dropped:
/// that removes exact degeneracies only (the solver itself refuses a fit
/// by the condition number of `JᵀJ`, so a fitted model has none).
fn operator(
    fit: &SensorFit,
    poses: &PoseTable,
    idx: usize,
    resid: &[Vec<Option<f64>>],
) -> Option<Operator> {
    let mut rows = Vec::new();
    let mut jac = Vec::new();
    for (k, row) in resid.iter().enumerate() {
        if row.get(idx).copied().flatten().is_some() {
            jac.push(jacobian_row(fit, poses, k, idx)?);
            rows.push(k);
        }
    }
    let (n, p) = (rows.len(), jac.first().map_or(0, Vec::len));
    if n == 0 || p == 0 {
        // a sensor without readings: nothing of it enters the energies
        return Some(Operator {
            rows,
            r: DMatrix::zeros(0, 0),
        });
    }
    let mut j = DMatrix::from_fn(n, p, |a, b| jac[a][b]);
    if j.iter().any(|x| !x.is_finite()) {
        return None;
    }
    for mut c in j.column_iter_mut() {
        let norm = c.norm();
        if norm > 0.0 {
            c /= norm;
        }
    }
    let svd = j.svd(true, false);
    let u = svd.u?;
    let smax = svd.singular_values.max();
    let keep: Vec<usize> = (0..svd.singular_values.len())
        .filter(|&c| svd.singular_values[c] > 1e-9 * smax)
        .collect();
    let ur = u.select_columns(&keep);
    let r = DMatrix::identity(n, n) - &ur * ur.transpose();
    Some(Operator { rows, r })
}

/// Orthonormal basis (as rows per sensor slot) of the plane columns of the
/// sensors `idx` in pose `k`; `None` for a pose left out (fewer than four
/// readings, a beam parallel to the plane).
fn plane_basis(
    geom: &[Sensor<f64>],
    poses: &PoseTable,
    k: usize,
    idx: &[usize],
) -> Option<Vec<Vec<f64>>> {
    if idx.len() < 4 {
        return None;
    }
    let a = plane_columns(geom, poses, k, idx)?;
    Some(orthonormal(&a))
}

/// Per pose: the sensors read and their plane basis.
type Bases = Vec<Option<(Vec<usize>, Vec<Vec<f64>>)>>;

/// (outside, inside) energy of residual-like values `v[pose][sensor]`.
fn energies(bases: &Bases, v: &[Vec<f64>]) -> (f64, f64) {
    let (mut w, mut i) = (0.0, 0.0);
    for (k, b) in bases.iter().enumerate() {
        let Some((idx, basis)) = b else { continue };
        let r: Vec<f64> = idx.iter().map(|&s| v[k][s]).collect();
        let total: f64 = r.iter().map(|x| x * x).sum();
        let inside: f64 = basis
            .iter()
            .map(|b| b.iter().zip(&r).map(|(x, y)| x * y).sum::<f64>().powi(2))
            .sum();
        w += (total - inside).max(0.0);
        i += inside;
    }
    (w, i)
}

/// The moment equations of the residuals `resid[pose][sensor]` of the fits
/// `fits`, with the nominal tracker `t0` (`None`: no plane error). `None`
/// when an operator cannot be formed (a prediction fails).
pub fn moments(
    fits: &[SensorFit],
    poses: &PoseTable,
    resid: &[Vec<Option<f64>>],
    t0: Option<&Tracker>,
) -> Option<Moments> {
    let ns = fits.len();
    if resid.len() != poses.len() || resid.iter().any(|r| r.len() < ns) {
        return None;
    }
    let geom: Vec<Sensor<f64>> = fits.iter().map(|f| f.sensor).collect();
    let bases: Bases = resid
        .iter()
        .enumerate()
        .map(|(k, row)| {
            let idx: Vec<usize> = (0..row.len().min(ns))
                .filter(|&i| row[i].is_some())
                .collect();
            plane_basis(&geom, poses, k, &idx).map(|b| (idx, b))
        })
        .collect();
    let ops: Vec<Operator> = (0..ns)
        .map(|i| operator(&fits[i], poses, i, resid))
        .collect::<Option<_>>()?;
    let measured: Vec<Vec<f64>> = resid
        .iter()
        .map(|row| {
            (0..ns)
                .map(|i| row.get(i).copied().flatten().unwrap_or(0.0))
                .collect()
        })
        .collect();
    let (w, i) = energies(&bases, &measured);
    let mut m = Moments {
        w,
        i,
        ..Moments::default()
    };
    reading_part(&mut m, fits, poses, &ops, &bases);
    if let Some(t) = t0 {
        plane_part(&mut m, fits, poses, &ops, &bases, t);
    }
    Some(m)
}

/// The run `inner` with its planes replaced by `planes` (when given) and
/// reading `bump.1` of pose `bump.0` raised by 1 mm (when given).
struct Perturbed<'a> {
    inner: &'a PoseTable,
    planes: Option<&'a [Plane<f64>]>,
    bump: Option<(usize, usize)>,
}

impl Poses<f64> for Perturbed<'_> {
    fn len(&self) -> usize {
        self.inner.len()
    }
    fn sensors(&self) -> usize {
        self.inner.sensors()
    }
    fn plane(&self, k: usize) -> Plane<f64> {
        match self.planes.and_then(|p| p.get(k)) {
            Some(p) => *p,
            None => self.inner.plane(k),
        }
    }
    fn reading(&self, k: usize, sensor: usize) -> Option<f64> {
        let d = self.inner.reading(k, sensor)?;
        Some(if self.bump == Some((k, sensor)) {
            d + 1.0
        } else {
            d
        })
    }
    fn context(&self, k: usize) -> perpend_core::ext::Context<f64> {
        self.inner.context(k)
    }
}

/// `U₁`, `T₁`: unit reading noise on each reading `(k, j)` in turn. It
/// enters its own residual whole and, through terms that read another
/// channel (the carry-over), the predictions of the pose's other sensors
/// with their coefficient; each sensor's part goes through its operator.
/// Exact (a sum over readings, no draws); a prediction's dependence on its
/// own reading is zero by construction (no leakage) and is not used.
fn reading_part(
    m: &mut Moments,
    fits: &[SensorFit],
    poses: &PoseTable,
    ops: &[Operator],
    bases: &Bases,
) {
    let ns = fits.len();
    let slot: Vec<Vec<Option<usize>>> = ops
        .iter()
        .map(|op| {
            let mut v = vec![None; poses.len()];
            op.rows
                .iter()
                .enumerate()
                .for_each(|(a, &k)| v[k] = Some(a));
            v
        })
        .collect();
    let mut v = vec![vec![0.0; ns]; poses.len()];
    for (j, op) in ops.iter().enumerate() {
        for &k in &op.rows {
            let bumped = Perturbed {
                inner: poses,
                planes: None,
                bump: Some((k, j)),
            };
            // coefficient of ε_kj in each sensor's residual of pose k
            let coef: Vec<f64> = (0..ns)
                .map(|i| match i == j {
                    true => 1.0,
                    false => match (
                        predict(&fits[i], &bumped, k, i),
                        predict(&fits[i], poses, k, i),
                    ) {
                        (Some(a), Some(b)) => b - a,
                        _ => 0.0,
                    },
                })
                .collect();
            v.iter_mut()
                .for_each(|row| row.iter_mut().for_each(|x| *x = 0.0));
            for (i, &c) in coef.iter().enumerate() {
                let Some(a) = slot[i][k] else { continue };
                if c == 0.0 {
                    continue;
                }
                for (b, &kk) in ops[i].rows.iter().enumerate() {
                    v[kk][i] += c * ops[i].r[(b, a)];
                }
            }
            let (w, t) = energies(bases, &v);
            m.u1 += w;
            m.t1 += t;
        }
    }
}

/// `U₂`, `T₂` and the spot energy: draws of the tracker `t` on the run's
/// planes, the change they make to each fitted prediction (its extension
/// terms included: a term built from the predicted distance, such as the
/// carry-over `d_src − d`, follows the plane error with its coefficient
/// and takes that share out of the residual) pushed through the operators.
fn plane_part(
    m: &mut Moments,
    fits: &[SensorFit],
    poses: &PoseTable,
    ops: &[Operator],
    bases: &Bases,
    t: &Tracker,
) {
    let ns = fits.len();
    let (mut u2, mut t2, mut spot, mut count) = (0.0, 0.0, 0.0, 0usize);
    let base: Vec<Vec<Option<f64>>> = (0..poses.len())
        .map(|k| (0..ns).map(|i| predict(&fits[i], poses, k, i)).collect())
        .collect();
    for j in 0..DRAWS {
        let mut rng = rand::rngs::StdRng::seed_from_u64(0x7A11 + j);
        let planes: Vec<Plane<f64>> = (0..poses.len())
            .map(|k| t.measure(&poses.plane(k), &mut rng))
            .collect();
        let seen = Perturbed {
            inner: poses,
            planes: Some(&planes),
            bump: None,
        };
        let mut r = vec![vec![0.0; ns]; poses.len()];
        for (i, op) in ops.iter().enumerate() {
            let e: Vec<f64> = op
                .rows
                .iter()
                .map(|&k| match (predict(&fits[i], &seen, k, i), base[k][i]) {
                    (Some(a), Some(b)) => a - b,
                    _ => 0.0,
                })
                .collect();
            for &k in &op.rows {
                let s = &fits[i].sensor;
                if let (Ok(a), Ok(b)) =
                    (distance(s, &planes[k], i), distance(s, &poses.plane(k), i))
                {
                    spot += (a - b) * (a - b);
                    count += 1;
                }
            }
            let out = &op.r * nalgebra::DVector::from_vec(e);
            for (a, &k) in op.rows.iter().enumerate() {
                r[k][i] = out[a];
            }
        }
        let (w, i) = energies(bases, &r);
        u2 += w;
        t2 += i;
    }
    m.u2 = u2 / DRAWS as f64;
    m.t2 = t2 / DRAWS as f64;
    m.spot = if count > 0 { spot / count as f64 } else { 0.0 };
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// Energies made from known values are solved back exactly; a plane
    /// part below two standard errors of the reading noise's is none.
    #[test]
    fn the_moment_equations_are_solved_and_unresolved_planes_are_none() {
        let m0 = Moments {
            u1: 50.0,
            u2: 4e-5,
            t1: 150.0,
            t2: 6e-3,
            ..Moments::default()
        };
        let at = |var: f64, s: f64| Moments {
            w: var * m0.u1 + s * m0.u2,
            i: var * m0.t1 + s * m0.t2,
            ..m0
        };
        let x = at(1e-4, 9.0).solve().unwrap();
        assert_relative_eq!(x.var, 1e-4, max_relative = 1e-9);
        assert_relative_eq!(x.scale, 9.0, max_relative = 1e-9);
        assert!(x.resolved);
        // 2·σ²·√(2·(T₁ + T₁²/U₁)) = 7.0e-3 against s·T₂ = 6e-5: not
        // resolved, but kept (it is the estimate)
        let x = at(1e-4, 0.01).solve().unwrap();
        assert!(!x.resolved);
        assert_relative_eq!(x.scale, 0.01, max_relative = 1e-6);
        // no plane part at all, the inside energy a little short: none
        let x = Moments {
            i: 0.9 * 1e-4 * m0.t1,
            ..at(1e-4, 0.0)
        }
        .solve()
        .unwrap();
        assert_eq!((x.scale, x.resolved), (0.0, false));
        assert_relative_eq!(x.var, 1e-4, max_relative = 1e-12);
        // no reading noise at all: the inside energy is the plane's
        let x = at(0.0, 4.0).solve().unwrap();
        assert_eq!(x.var, 0.0);
        assert_relative_eq!(x.scale, 4.0, max_relative = 1e-9);
        // resolved only beyond two standard errors of I − (T₁/U₁)·W
        let se = 1e-4 * (2.0 * (m0.t1 + m0.t1 * m0.t1 / m0.u1)).sqrt();
        let s_edge = 2.0 * se / m0.t2;
        assert!(!at(1e-4, 0.9 * s_edge).solve().unwrap().resolved);
        assert!(at(1e-4, 1.1 * s_edge).solve().unwrap().resolved);
        // no within-pose equations: nothing to solve
        assert_eq!(Moments { u1: 0.0, ..m0 }.solve(), None);
    }
}

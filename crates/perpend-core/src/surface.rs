//! The surface normal where the spindle axis meets a **curved** skin of
//! known nominal shape: plane, sphere or circular cylinder.
//!
//! ## What the micro-plane gets wrong
//!
//! Both papers fit a micro-plane to the spots (Chen §4.1, eq. 18-19; Tian
//! §3, the "numerous tiny planes" hypothesis) and take its normal as the
//! normal at the drilling point. On a surface of radius `R` the plane
//! through the spots has (nearly) the normal of the surface at the centre of
//! the spot pattern, not at the point `P` where the spindle axis (TCS z)
//! meets the surface. For a cone head (beams at half-angle `λ` to the axis,
//! spots on a circle of radius `ρ` at the standoff) tilted by `θ`, the spots
//! on the far side run further along their converging beams: with Tian
//! eq. 6-8 the spot of a pair sits at `l/2 − h·sin λ` from the axis, so the
//! pair's midpoint moves by `ρ·tan λ·tan θ` to first order. The plane's
//! normal then errs by
//!
//! ```text
//! ε_plane ≈ (ρ·tan λ·tan θ + δ0) / R   [rad]
//! ```
//!
//! where `δ0` is how far the pattern's centre lies off the axis at `θ = 0`
//! (the zero points and beams of a real head are not symmetric; errors of
//! Chen Table 2's size put it at a few mm). On a cylinder only the part
//! across the cylinder's axis counts. A Tian-style head (`λ` = 25°, zero
//! points on a 45 mm circle, standoff 60 mm: `ρ` = 17.0 mm) on a cylinder
//! of `R` = 500 mm tilted by 10° across its axis: 0.160° to first order,
//! 0.192° exactly (golden test); `perpend bench curvature` measures it with
//! calibrated heads (docs/curvature.md).
//!
//! ## Method
//!
//! 1. Spots and micro-plane as today ([`crate::normal::plane_and_spots`]:
//!    Chen eq. 17 with the sensors' extension corrections, then least
//!    squares or Chen eq. 18-19): centroid `m`, normal `n0` towards the head.
//! 2. The surface (signed radius `R`, `s = sign R`, `r = |R|`) is written
//!    as a point `p0 = m + h·g` on the line through `m` along `g = n0` and
//!    the unit normal `n` there (towards the head; a cylinder's axis `a` is
//!    the given direction projected perpendicular to `n`); the
//!    sphere's centre or a point of the cylinder's axis is
//!    `c = p0 − s·r·n`. With `v = q − p0` for a spot `q` and `P` the
//!    projection across the cylinder's axis (identity for a sphere), the
//!    orthogonal residual of the spot is
//!
//!    ```text
//!    e = s·(|P(q − c)| − r) = (s·|Pv|² + 2r·(v·n)) / (|Pv + s·r·n| + r)
//!    ```
//!
//!    in a form without cancellation (every term is of the size of the spot
//!    pattern, so it runs in `f32` for radii up to ~10⁴ mm); it tends to
//!    the plane's `v·n` as `r → ∞`.
//! 3. Gauss-Newton on the free pose parameters `(h, α, β)` — sphere: the
//!    centre; cylinder: the axis' position across and its elevation (the
//!    azimuth is given, below) — with the tilts as a retraction
//!    `n' = normalise(n + α·t1 + β·t2)` as for the beams in
//!    [`crate::head`]. Jacobian, with `w = Pv + s·r·n`, `u = w/|w|`:
//!    `∂e/∂h = −s·u·g`, `∂e/∂α = r·(v·t1)/|w|` (sphere; the cylinder adds
//!    the turn of its projected axis, see `Problem::gradient`). Start:
//!    `n = g` and the sagitta `h = s·mean|v_⊥|²/(2r)`. The problem is
//!    nearly linear: measured from this start, the step after a step of
//!    `δ` rad is at most [`CONTRACTION`]`·δ²` (R ≥ 2× the spot spread,
//!    tilt ≤ 20°, reading noise up to ±0.1 mm). So the fit stops as soon
//!    as that predicted next step is below `0.01·√ε` (and the step in `h`
//!    below `δ·spread`): one step in `f32` when `δ` ≤ 4.1·10⁻³ rad, two
//!    beyond, instead of the confirming step a converged fit would take
//!    (test `one_step_is_converged`; under the factory head on a 300 mm
//!    sphere: one step up to ~10° of tilt, two at 15-17°, `cargo xtask
//!    mcu-bench`). At most [`MAX_ITERATIONS`].
//! 4. The spindle axis `z·e_z` meets `|P(z·e_z − c)| = r` where
//!    `A·z² + 2B·z + C = 0`, `A = |P e_z|²`, `B = s·r·n_z − (P e_z)·p0`,
//!    `C = |P p0|² − 2s·r·(n·p0)`; the root where the normal faces the head
//!    (`n_z < 0`: the first hit from the head for a convex skin, the one
//!    ahead for a concave one) is `z = C / (s·√(B² − A·C) − B)` (the
//!    cancellation-free form). The normal there is
//!    `normalise(n + s·P(z·e_z − p0)/r)`.
//! 5. Deviation θ1/θ2/θ (Tian eq. 1-5) and pitch/yaw (Chen eq. 22) from
//!    that normal, with [`crate::angles`].
//!
//! [`Shape::Plane`] is today's measurement unchanged ([`crate::normal`]),
//! with the point where the axis meets the plane.
//!
//! **Convex or concave**: the radius is signed. `R > 0` is convex (the skin
//! bulges towards the head, its centre or axis lies beyond the surface: the
//! outside of a fuselage); `R < 0` is concave (the centre is on the head's
//! side: the inside of a barrel).
//!
//! **The cylinder's axis azimuth is given, not fitted.** Four spots on a
//! cross leave one degree of freedom beyond the plane: the twist of the
//! heights, `∝ cos 2ψ` for an axis at azimuth `ψ`. It cannot tell `ψ` from
//! `−ψ`, and is stationary at `ψ` = 0° and 90°, so a fitted direction would
//! be ambiguous or ill-conditioned exactly where heads usually look. The
//! direction comes from the part's CAD and the robot's pose, in the TCS.
//! Its **elevation is not trusted**: a real axis lies in the tangent plane,
//! and a head tilted along the axis (the tilt being measured) sees it out of
//! the nominal tangent plane by that tilt; holding the given direction
//! fixed would force the normal perpendicular to it, an error as large as
//! the tilt. So the given direction is projected on the tangent plane at
//! `p0` at every iteration (`a = normalise(a₀ − (a₀·n)·n)`), the fit keeps
//! 3 unknowns (height, two tilts: the axis' position across and its
//! elevation) and one residual degree of freedom for 4 spots.
//!
//! ## Error model of the curved fit
//!
//! With the right shape, radius and axis azimuth the bias above is gone and
//! what remains is the noise of the readings, of the same size as the
//! plane's (3 unknowns for 4 spots, as the plane), and the head's
//! calibration, as for a plane: `perpend bench curvature` finds the curved
//! model with a calibrated head within 1.06× of the true head for
//! `R` ≥ 300 mm and tilts ≤ 10°. What the nominal shape gets wrong stays:
//! a radius off by `ΔR` leaves `ε_plane·|ΔR|/R_used` (golden test), a
//! cylinder axis azimuth off by `Δψ` about `ε_plane·sin Δψ` (bench:
//! `--radius-err`, `--axis-err-deg`); waviness, a second curvature or a
//! radius that changes over the pattern are not modelled. The normal is
//! extrapolated from the pattern's centre to the axis point, over a few mm
//! for a calibrated head (no measurable noise gain in the bench).
//!
//! ## Limits and errors
//!
//! * ≥ 3 spots ([`Error::TooFewReadings`]), not collinear
//!   ([`Error::DegenerateSpots`]);
//! * `|R|` at least twice the spots' largest distance from their centroid
//!   across the surface ([`Error::SurfaceTooCurved`]); radius zero, NaN or
//!   infinite: [`Error::OutOfRange`]/[`Error::NonFinite`]; a cylinder axis
//!   within 60° of the measured normal (`|n0·a| > 0.5`) is no cylinder the
//!   spots lie on: [`Error::OutOfRange`];
//! * the axis passes beside the fitted sphere or cylinder or runs parallel
//!   to the cylinder: [`Error::AxisMissesSurface`];
//! * no convergence in [`MAX_ITERATIONS`], or a step that turns the normal
//!   by more than [`MAX_STEP_RAD`]: [`Error::NoConvergence`];
//! * a sensor's incidence correction ([`crate::ext`]) takes the angle γ
//!   from the micro-plane's normal, not from the local normal at its spot
//!   (they differ by ≤ ρ/R rad, a negligible change of `1/cos γ`);
//! * no allocation; fixed-size `SMatrix`; generic over [`Real`].

use nalgebra::{SMatrix, SVector, Vector3};

use crate::angles::{Attitude, Deviation};
use crate::ext::Context;
use crate::ext::Prepared;
use crate::geometry::{tangent_basis, unit};
use crate::head::Head;
use crate::normal::{degenerate_tol, plane_and_spots_with, prepare, Method, PlaneFit};
use crate::{finite, Error, Real, Result};

/// Gauss-Newton iterations before [`Error::NoConvergence`].
pub const MAX_ITERATIONS: usize = 12;

/// Bound `K` [1/rad] on the fit's contraction from the micro-plane start:
/// a step of `δ` rad is followed by one of at most `K·δ²`. Measured
/// (largest next-step/step² over spheres and cylinders of ±300-5000 mm,
/// tilts to 20°, reading noise to ±0.1 mm, steps above 10⁻³ rad): 0.11;
/// twice that here.
pub const CONTRACTION: f64 = 0.2;

/// Largest tilt of the normal [rad] one Gauss-Newton step may make (30°);
/// a larger one means the start was outside the fit's basin.
pub const MAX_STEP_RAD: f64 = 0.5;

/// `|R|` must be at least this multiple of the spots' largest distance from
/// their centroid across the surface (30° of arc).
pub const MIN_RADIUS_RATIO: f64 = 2.0;

/// Largest `|n0·a|` between the micro-plane normal and a cylinder's axis
/// (the axis must lie within 30° of the micro-plane).
pub const MAX_AXIS_COS: f64 = 0.5;

/// Nominal shape of the surface under the head, in the TCS.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape<T: Real> {
    /// A plane: the micro-plane of [`crate::normal`], unchanged.
    Plane,
    /// A sphere of signed radius [mm]: `> 0` convex (bulging towards the
    /// head), `< 0` concave.
    Sphere {
        /// Signed radius [mm].
        radius: T,
    },
    /// A circular cylinder of signed radius [mm] (sign as for the sphere)
    /// whose axis has direction `axis` in the TCS (any length, either sense).
    Cylinder {
        /// Signed radius [mm].
        radius: T,
        /// Direction of the cylinder's axis in the TCS.
        axis: Vector3<T>,
    },
}

impl<T: Real> Shape<T> {
    /// The same shape in another precision (the host's `f64` as the
    /// board's `f32`).
    pub fn cast<U: Real>(&self) -> Shape<U> {
        let c = |x: T| U::lit(x.to_f64());
        match *self {
            Shape::Plane => Shape::Plane,
            Shape::Sphere { radius } => Shape::Sphere { radius: c(radius) },
            Shape::Cylinder { radius, axis } => Shape::Cylinder {
                radius: c(radius),
                axis: Vector3::new(c(axis.x), c(axis.y), c(axis.z)),
            },
        }
    }
}

/// The surface fitted to the spots and its normal at the spindle axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceFit<T: Real> {
    /// The micro-plane (the fit's start; the answer for [`Shape::Plane`]).
    pub plane: PlaneFit<T>,
    /// Where the spindle axis meets the fitted surface [mm, TCS].
    pub point: Vector3<T>,
    /// Unit surface normal at `point`, towards the head.
    pub normal: Vector3<T>,
    /// RMS orthogonal distance of the used spots from the fitted surface
    /// [mm] (the plane's RMS for [`Shape::Plane`]).
    pub rms: T,
    /// Gauss-Newton iterations made (0 for [`Shape::Plane`]).
    pub iterations: usize,
}

/// A complete measurement on a surface of known shape.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfaceMeasurement<T: Real> {
    /// The fitted surface and the normal at the axis point.
    pub fit: SurfaceFit<T>,
    /// Tian's deviation of the spindle from that normal (eq. 1-5).
    pub deviation: Deviation<T>,
    /// Chen's attitude correction (eq. 22).
    pub attitude: Attitude<T>,
}

/// A validated curved shape: sign, radius, cylinder axis.
#[derive(Debug, Clone, Copy)]
struct Curved<T: Real> {
    /// +1 convex, −1 concave.
    s: T,
    /// |R| [mm].
    r: T,
    /// Unit cylinder axis (`None`: sphere).
    axis: Option<Vector3<T>>,
}

impl<T: Real> Curved<T> {
    fn new(shape: &Shape<T>) -> Result<Option<Self>> {
        let (radius, axis) = match shape {
            Shape::Plane => return Ok(None),
            Shape::Sphere { radius } => (*radius, None),
            Shape::Cylinder { radius, axis } => (*radius, Some(unit(*axis, "cylinder axis")?)),
        };
        finite(radius, "surface radius")?;
        if radius == T::zero() {
            return Err(Error::OutOfRange("surface radius"));
        }
        let s = if radius > T::zero() {
            T::one()
        } else {
            -T::one()
        };
        Ok(Some(Self {
            s,
            r: radius.abs(),
            axis,
        }))
    }

    /// `P v`: `v` without its component along the cylinder's axis.
    fn proj(&self, v: &Vector3<T>) -> Vector3<T> {
        match &self.axis {
            Some(a) => v - a * a.dot(v),
            None => *v,
        }
    }
}

/// Where the fit stands: `p0 = m + h·g` and the normal `n` there.
#[derive(Debug, Clone, Copy)]
struct State<T: Real> {
    h: T,
    n: Vector3<T>,
}

/// The fixed part of the fit: the shape, the centroid `m` of the used
/// spots, the direction `g` of the line `p0` moves on, and the used spots
/// relative to `m` (`q − m`, formed once).
struct Problem<'a, T: Real> {
    c: Curved<T>,
    m: Vector3<T>,
    g: Vector3<T>,
    pts: &'a [Vector3<T>],
}

/// One spot against the current surface: residual `e`, `v = q − p0`,
/// `w = P(v + s·r·n)` and `|w|`.
struct SpotResidual<T: Real> {
    e: T,
    v: Vector3<T>,
    w: Vector3<T>,
    wl: T,
}

impl<T: Real> Problem<'_, T> {
    /// The shape at normal `n`: a cylinder's given axis projected on the
    /// tangent plane (its elevation follows the normal, module docs).
    fn at(&self, n: &Vector3<T>) -> Result<Curved<T>> {
        let axis = match &self.c.axis {
            Some(a) => {
                Some(unit(a - n * n.dot(a), "cylinder axis").map_err(|_| Error::NoConvergence)?)
            }
            None => None,
        };
        Ok(Curved { axis, ..self.c })
    }

    /// Residual of spot `q` (module docs, step 2; `q` relative to `m`) on
    /// the shape `c` (from [`Problem::at`] for `st.n`).
    fn residual(&self, c: &Curved<T>, st: &State<T>, q: &Vector3<T>) -> SpotResidual<T> {
        let v = q - self.g * st.h;
        let pv = c.proj(&v);
        let vn = v.dot(&st.n);
        let ww = pv.norm_squared() * c.s + c.r * vn * T::lit(2.0);
        // |w|² = r² + s·ww ≥ 0 in exact arithmetic.
        let wl = larger(c.r * c.r + ww * c.s, T::zero()).fast_sqrt();
        SpotResidual {
            e: ww / (wl + c.r),
            v,
            w: pv + st.n * (c.s * c.r),
            wl,
        }
    }

    /// Gradient row `(∂e/∂h, ∂e/∂α, ∂e/∂β)` of one spot for the tilts `t`.
    /// With `f = |w|² = |v + s·r·n|² − (a·v)²` (`a` the projected axis),
    /// `∂e/∂x = s·(∂f/∂x)/(2|w|)`; the axis turns with the normal:
    /// `∂a/∂α = −P_a((a₀·t)·n + (a₀·n)·t)/|a₀ − (a₀·n)n|`.
    fn gradient(
        &self,
        c: &Curved<T>,
        st: &State<T>,
        t: &[Vector3<T>; 2],
        sr: &SpotResidual<T>,
    ) -> SVector<T, 3> {
        let (s, r) = (c.s, c.r);
        let mut j = SVector::<T, 3>::new(-s * sr.w.dot(&self.g) / sr.wl, T::zero(), T::zero());
        for (k, tk) in t.iter().enumerate() {
            // ½ ∂f/∂α_k
            let mut half = s * r * sr.v.dot(tk);
            if let (Some(a0), Some(a)) = (&self.c.axis, &c.axis) {
                let b = a0 - st.n * st.n.dot(a0);
                let db = -(st.n * a0.dot(tk) + tk * a0.dot(&st.n)) / b.norm_squared().fast_sqrt();
                let da = db - a * a.dot(&db);
                half -= a.dot(&sr.v) * sr.v.dot(&da);
            }
            j[k + 1] = s * half / sr.wl;
        }
        j
    }

    /// Normal equations `JᵀJ` (upper triangle), `−Jᵀe` at `st` for the
    /// tangent basis `t` of `st.n`.
    fn normal_equations(
        &self,
        st: &State<T>,
        t: &[Vector3<T>; 2],
    ) -> Result<(SMatrix<T, 3, 3>, SVector<T, 3>)> {
        let c = self.at(&st.n)?;
        let mut a = SMatrix::<T, 3, 3>::zeros();
        let mut b = SVector::<T, 3>::zeros();
        for q in self.pts {
            let sr = self.residual(&c, st, q);
            let j = self.gradient(&c, st, t, &sr);
            for r in 0..3 {
                for k in r..3 {
                    a[(r, k)] += j[r] * j[k];
                }
            }
            b -= j * sr.e;
        }
        Ok((a, b))
    }

    /// Sum of squared residuals at `st`.
    fn sum_squares(&self, st: &State<T>) -> Result<T> {
        let c = self.at(&st.n)?;
        Ok(self.pts.iter().fold(T::zero(), |acc, q| {
            let e = self.residual(&c, st, q).e;
            acc + e * e
        }))
    }
}

/// The larger of `a` and `b` (`b` when `a` is NaN), inline: `f32::max`
/// is a call to libm's `fmaxf` on the board.
#[inline]
fn larger<T: Real>(a: T, b: T) -> T {
    if a > b {
        a
    } else {
        b
    }
}

/// Solves `A x = b` for a symmetric `A` given by its upper triangle, by
/// `LDLᵀ` without square roots. A pivot `d_i` below `√ε·a_ii` means the
/// spots do not determine the unknowns: the same test as a Cholesky factor
/// of `A` scaled to unit diagonal (whose `l_ii²` is `d_i/a_ii`).
fn solve_ldl<T: Real, const K: usize>(
    a: &SMatrix<T, K, K>,
    b: &SVector<T, K>,
) -> Result<SVector<T, K>> {
    let tol = degenerate_tol::<T>();
    let mut l = SMatrix::<T, K, K>::identity();
    let mut d = SVector::<T, K>::zeros();
    for i in 0..K {
        let mut di = a[(i, i)];
        for k in 0..i {
            di -= l[(i, k)] * l[(i, k)] * d[k];
        }
        if !(di > tol * a[(i, i)]) || !(a[(i, i)] > T::zero()) {
            return Err(Error::DegenerateSpots);
        }
        d[i] = di;
        for j in i + 1..K {
            let mut v = a[(i, j)];
            for k in 0..i {
                v -= l[(j, k)] * l[(i, k)] * d[k];
            }
            l[(j, i)] = v / di;
        }
    }
    let mut x = *b;
    for i in 0..K {
        for k in 0..i {
            x[i] = x[i] - l[(i, k)] * x[k];
        }
    }
    for i in (0..K).rev() {
        x[i] /= d[i];
        for k in i + 1..K {
            x[i] = x[i] - l[(k, i)] * x[k];
        }
    }
    Ok(x)
}

/// Gauss-Newton on `(h, α, β)` from `st`; returns the iterations made.
/// `spread2`: the spots' largest squared distance across the surface from
/// their centroid (from [`start`]), the scale of the `h` step's test.
fn gauss_newton<T: Real>(pb: &Problem<'_, T>, st: &mut State<T>, spread2: T) -> Result<usize> {
    // The next step would be at most K·δ²: stop when that is below tol
    // (compared squared: δ² ≤ tol/K).
    let stop2 = degenerate_tol::<T>() * T::lit(0.01 / CONTRACTION);
    let max2 = T::lit(MAX_STEP_RAD * MAX_STEP_RAD);
    for it in 1..=MAX_ITERATIONS {
        let (e1, e2) = tangent_basis(&st.n);
        let (a, b) = pb.normal_equations(st, &[e1, e2])?;
        let d = solve_ldl(&a, &b)?;
        let tilt = e1 * d[1] + e2 * d[2];
        let step2 = tilt.norm_squared();
        if !(step2 <= max2) || !d[0].is_finite_real() {
            return Err(Error::NoConvergence);
        }
        st.h += d[0];
        st.n = unit(st.n + tilt, "fitted normal").map_err(|_| Error::NoConvergence)?;
        if step2 <= stop2 && d[0] * d[0] <= stop2 * spread2 {
            return Ok(it);
        }
    }
    Err(Error::NoConvergence)
}

/// The start of the fit (module docs, step 3) after the radius check, and
/// the spots' largest squared distance across the surface from `m`.
fn start<T: Real>(pb: &Problem<'_, T>) -> Result<(State<T>, T)> {
    let c = pb.at(&pb.g)?;
    let (mut sum, mut max) = (T::zero(), T::zero());
    for q in pb.pts {
        let pv = c.proj(q);
        let lat2 = (pv - pb.g * pv.dot(&pb.g)).norm_squared();
        sum += lat2;
        max = larger(lat2, max);
    }
    let ratio = T::lit(MIN_RADIUS_RATIO);
    if !(pb.c.r * pb.c.r >= ratio * ratio * max) {
        return Err(Error::SurfaceTooCurved);
    }
    let mean = sum / T::lit(pb.pts.len() as f64);
    let st = State {
        h: pb.c.s * mean / (T::lit(2.0) * pb.c.r),
        n: pb.g,
    };
    Ok((st, max))
}

/// Where the spindle axis meets the fitted surface and the normal there
/// (module docs, step 4).
fn intersect_axis<T: Real>(
    c: &Curved<T>,
    p0: &Vector3<T>,
    n: &Vector3<T>,
) -> Result<(Vector3<T>, Vector3<T>)> {
    let ez = Vector3::z();
    let pz = c.proj(&ez);
    let pp0 = c.proj(p0);
    let a = pz.norm_squared();
    // The axis parallel to a cylinder's axis (within ~0.6°) never meets it.
    if !(a > T::lit(1e-4)) {
        return Err(Error::AxisMissesSurface);
    }
    let b = c.s * c.r * n.z - pz.dot(p0);
    let cc = pp0.norm_squared() - T::lit(2.0) * c.s * c.r * n.dot(p0);
    let disc = b * b - a * cc;
    if !(disc >= T::zero()) {
        return Err(Error::AxisMissesSurface);
    }
    let den = c.s * disc.fast_sqrt() - b;
    let z = cc / den;
    if !z.is_finite_real() {
        return Err(Error::AxisMissesSurface);
    }
    let point = ez * z;
    let normal = unit(*n + c.proj(&(point - p0)) * (c.s / c.r), "surface normal")?;
    Ok((point, normal))
}

/// Where the spindle axis meets the micro-plane (for [`Shape::Plane`]).
fn plane_point<T: Real>(p: &PlaneFit<T>) -> Result<Vector3<T>> {
    let z = p.normal.dot(&p.centroid) / p.normal.z;
    if !z.is_finite_real() {
        return Err(Error::AxisMissesSurface);
    }
    Ok(Vector3::z() * z)
}

/// Fits the curved shape `c` to the used spots, starting from `plane`.
/// Not inlined: kept out of the plane-only path's frame on the board.
#[inline(never)]
fn fit_curved<T: Real, const N: usize>(
    c: Curved<T>,
    plane: &PlaneFit<T>,
    spots: &[Option<Vector3<T>>; N],
) -> Result<SurfaceFit<T>> {
    let mut buf = [Vector3::<T>::zeros(); N];
    let mut k = 0;
    for p in spots.iter().flatten() {
        buf[k] = p - plane.centroid;
        k += 1;
    }
    if let Some(a) = &c.axis {
        if !(plane.normal.dot(a).abs() <= T::lit(MAX_AXIS_COS)) {
            return Err(Error::OutOfRange("cylinder axis along the normal"));
        }
    }
    let pb = Problem {
        c,
        m: plane.centroid,
        g: plane.normal,
        pts: &buf[..k],
    };
    let (mut st, spread2) = start(&pb)?;
    let iterations = gauss_newton(&pb, &mut st, spread2)?;
    let ss = pb.sum_squares(&st)?;
    let p0 = pb.m + pb.g * st.h;
    let (point, normal) = intersect_axis(&pb.at(&st.n)?, &p0, &st.n)?;
    Ok(SurfaceFit {
        plane: *plane,
        point,
        normal,
        rms: (ss / T::lit(k as f64)).fast_sqrt(),
        iterations,
    })
}

/// Readings to the surface fit: spots and micro-plane
/// ([`crate::normal::plane_and_spots`]), then the nominal shape fitted to
/// the spots and its normal where the spindle axis meets it.
///
/// # Errors
/// Those of [`crate::normal::plane`], and those listed in the module docs.
pub fn fit<T: Real, const N: usize>(
    head: &Head<T, N>,
    readings: &[Option<T>; N],
    ctx: &Context<T>,
    method: Method,
    shape: &Shape<T>,
) -> Result<SurfaceFit<T>> {
    fit_with(head, &prepare(head), readings, ctx, method, shape)
}

/// [`fit`] with the extensions prepared once
/// ([`crate::normal::prepare`] of `head`).
///
/// # Errors
/// As [`fit`].
pub fn fit_with<T: Real, const N: usize>(
    head: &Head<T, N>,
    prep: &[Prepared<T>; N],
    readings: &[Option<T>; N],
    ctx: &Context<T>,
    method: Method,
    shape: &Shape<T>,
) -> Result<SurfaceFit<T>> {
    let curved = Curved::new(shape)?;
    let (plane, spots) = plane_and_spots_with(head, prep, readings, ctx, method)?;
    match curved {
        None => Ok(SurfaceFit {
            plane,
            point: plane_point(&plane)?,
            normal: plane.normal,
            rms: plane.rms,
            iterations: 0,
        }),
        Some(c) => fit_curved(c, &plane, &spots),
    }
}

/// The whole computation on a surface of known shape: [`fit`], deviation
/// (Tian eq. 1-5) and attitude correction (Chen eq. 22). For
/// [`Shape::Plane`] the normal and angles are those of
/// [`crate::normal::measure`].
///
/// # Errors
/// Those of [`fit`], and [`Error::SurfaceFacesAway`].
pub fn measure<T: Real, const N: usize>(
    head: &Head<T, N>,
    readings: &[Option<T>; N],
    ctx: &Context<T>,
    method: Method,
    shape: &Shape<T>,
) -> Result<SurfaceMeasurement<T>> {
    measure_with(head, &prepare(head), readings, ctx, method, shape)
}

/// [`measure`] with the extensions prepared once
/// ([`crate::normal::prepare`] of `head`): the board's per-sample path.
///
/// # Errors
/// As [`measure`].
pub fn measure_with<T: Real, const N: usize>(
    head: &Head<T, N>,
    prep: &[Prepared<T>; N],
    readings: &[Option<T>; N],
    ctx: &Context<T>,
    method: Method,
    shape: &Shape<T>,
) -> Result<SurfaceMeasurement<T>> {
    let fit = fit_with(head, prep, readings, ctx, method, shape)?;
    let deviation = Deviation::from_normal(&fit.normal)?;
    Ok(SurfaceMeasurement {
        fit,
        deviation,
        attitude: Attitude::from_deviation(&deviation),
    })
}

/// A sphere or cylinder placed in the TCS: the exact geometry that
/// simulators and tests read (beam-surface intersection) and the truth a
/// fit is compared with. It works with the centre, so use `f64` for radii
/// above ~10³ mm (the fit itself does not need it, see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurvedSurface<T: Real> {
    /// Centre of the sphere, or a point on the cylinder's axis [mm].
    pub centre: Vector3<T>,
    /// Signed radius [mm] (`> 0` convex, `< 0` concave, as [`Shape`]).
    pub radius: T,
    /// Unit direction of the cylinder's axis (`None`: sphere).
    pub axis: Option<Vector3<T>>,
}

impl<T: Real> CurvedSurface<T> {
    /// The surface of `shape` that passes through `point` with normal
    /// `normal` there (any length; the side it points to is the head's
    /// side). A cylinder's axis is made perpendicular to `normal`.
    ///
    /// # Errors
    /// [`Error::OutOfRange`] for [`Shape::Plane`] or a cylinder axis along
    /// `normal`; those of invalid radii and vectors.
    pub fn through(point: Vector3<T>, normal: Vector3<T>, shape: &Shape<T>) -> Result<Self> {
        for x in point.iter() {
            finite(*x, "surface point")?;
        }
        let c = Curved::new(shape)?.ok_or(Error::OutOfRange("a plane is not curved"))?;
        let n = unit(normal, "surface normal")?;
        let axis = match c.axis {
            Some(a) => Some(
                unit(a - n * n.dot(&a), "cylinder axis")
                    .map_err(|_| Error::OutOfRange("cylinder axis along the normal"))?,
            ),
            None => None,
        };
        Ok(Self {
            centre: point - n * (c.s * c.r),
            radius: c.s * c.r,
            axis,
        })
    }

    /// The nominal shape (radius and axis direction) of this surface.
    pub fn shape(&self) -> Shape<T> {
        match self.axis {
            Some(axis) => Shape::Cylinder {
                radius: self.radius,
                axis,
            },
            None => Shape::Sphere {
                radius: self.radius,
            },
        }
    }

    fn curved(&self) -> Curved<T> {
        let s = if self.radius < T::zero() {
            -T::one()
        } else {
            T::one()
        };
        Curved {
            s,
            r: self.radius.abs(),
            axis: self.axis,
        }
    }

    /// Unit normal at the surface point `p`, towards the head's side
    /// (outwards for a convex surface, towards the centre for a concave one).
    ///
    /// # Errors
    /// [`Error::ZeroLength`] at the centre or on the axis.
    pub fn normal_at(&self, p: &Vector3<T>) -> Result<Vector3<T>> {
        let c = self.curved();
        unit(c.proj(&(p - self.centre)) * c.s, "surface normal")
    }

    /// Parameter `t` of the point `o + t·u` of the line where it meets the
    /// surface with the normal facing against `u` (the side the line comes
    /// from for a convex surface, the one ahead for a concave one), or
    /// `None` when it misses (or runs along a cylinder's axis).
    pub fn line_hit(&self, o: &Vector3<T>, u: &Vector3<T>) -> Option<T> {
        let c = self.curved();
        let pu = c.proj(u);
        let po = c.proj(&(o - self.centre));
        let a = pu.norm_squared();
        if !(a > T::lit(1e-12) * u.norm_squared()) {
            return None;
        }
        let b = pu.dot(&po);
        let cc = po.norm_squared() - c.r * c.r;
        let disc = b * b - a * cc;
        if !(disc >= T::zero()) {
            return None;
        }
        // B + t·A = −s·√D; of the two equal forms take the one without
        // cancellation.
        let sq = disc.sqrt() * c.s;
        let (near, far) = (-b - sq, -b + sq);
        let t = if near.abs() >= far.abs() {
            near / a
        } else {
            cc / far
        };
        t.is_finite_real().then_some(t)
    }

    /// The reading (geometric distance along the beam) of sensor `idx` on
    /// this surface: Chen eq. 3 with the surface instead of the plane.
    ///
    /// # Errors
    /// [`Error::BeamMissesSurface`] when the beam misses it,
    /// [`Error::PlaneBehindSensor`] when the surface is behind the sensor.
    pub fn distance(&self, sensor: &crate::head::Sensor<T>, idx: usize) -> Result<T> {
        let d = self
            .line_hit(&sensor.zero, &sensor.dir)
            .ok_or(Error::BeamMissesSurface(idx))?;
        if d < T::zero() {
            return Err(Error::PlaneBehindSensor(idx));
        }
        Ok(d)
    }

    /// Where the spindle axis (TCS z) meets the surface, and the unit normal
    /// there towards the head.
    ///
    /// # Errors
    /// [`Error::AxisMissesSurface`].
    pub fn axis_point(&self) -> Result<(Vector3<T>, Vector3<T>)> {
        let z = self
            .line_hit(&Vector3::zeros(), &Vector3::z())
            .ok_or(Error::AxisMissesSurface)?;
        let p = Vector3::z() * z;
        Ok((p, self.normal_at(&p)?))
    }

    /// The surface in another frame: `x' = rot·x + trans`.
    pub fn transformed(&self, rot: &nalgebra::Matrix3<T>, trans: &Vector3<T>) -> Self {
        Self {
            centre: rot * self.centre + trans,
            radius: self.radius,
            axis: self.axis.map(|a| rot * a),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::head::Head4;
    use crate::normal;
    use approx::assert_relative_eq;

    /// Tian-style head: cone 25°, zero points on a 45 mm circle (issue 14).
    fn tian_head() -> Head4<f64> {
        Head4::cone(45.0, 25f64.to_radians(), 0.0, 0.0).unwrap()
    }

    /// Unit normal towards the head tilted `tilt` from −z towards azimuth `az` [deg].
    fn tilted(tilt: f64, az: f64) -> Vector3<f64> {
        let (t, a) = (tilt.to_radians(), az.to_radians());
        Vector3::new(t.sin() * a.cos(), t.sin() * a.sin(), -t.cos())
    }

    fn readings<const N: usize>(head: &Head<f64, N>, s: &CurvedSurface<f64>) -> [Option<f64>; N] {
        core::array::from_fn(|i| Some(s.distance(&head.sensors[i], i).unwrap()))
    }

    fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
        a.cross(b).norm().atan2(a.dot(b)).to_degrees()
    }

    fn shapes(r: f64) -> [Shape<f64>; 4] {
        let axis = Vector3::new(1.0, 2.0, 0.3);
        [
            Shape::Sphere { radius: r },
            Shape::Sphere { radius: -r },
            Shape::Cylinder { radius: r, axis },
            Shape::Cylinder { radius: -r, axis },
        ]
    }

    #[test]
    fn exact_recovery_on_spheres_and_cylinders() {
        let head = tian_head();
        let ctx = Context::default();
        let p = Vector3::new(0.0, 0.0, 60.0);
        let n = tilted(10.0, 30.0);
        for shape in shapes(500.0) {
            let surf = CurvedSurface::through(p, n, &shape).unwrap();
            let (pt, nt) = surf.axis_point().unwrap();
            assert_relative_eq!(pt, p, epsilon = 1e-9);
            assert_relative_eq!(nt, n, epsilon = 1e-12);
            let r = readings(&head, &surf);
            let m = measure(&head, &r, &ctx, Method::LeastSquares, &surf.shape()).unwrap();
            assert_relative_eq!(m.fit.normal, n, epsilon = 1e-10);
            assert_relative_eq!(m.fit.point, p, epsilon = 1e-8);
            assert!(m.fit.rms < 1e-9, "{shape:?}: {}", m.fit.rms);
            assert!(m.fit.iterations <= 6, "{shape:?}: {}", m.fit.iterations);
            let want = Deviation::from_normal(&n).unwrap();
            assert_relative_eq!(m.deviation.theta, want.theta, epsilon = 1e-10);
            assert_relative_eq!(m.deviation.theta1, want.theta1, epsilon = 1e-10);
        }
    }

    #[test]
    fn plane_model_error_golden() {
        // Issue 14: Tian-style head, standoff 60 mm, cylinder R = 500 mm,
        // tilt 10° across its axis: the micro-plane errs by ~0.19°. The first-order
        // model of the module docs gives ρ·tan λ·tan θ / R with
        // ρ = 45 − 60·tan 25° = 17.02 mm: 0.160°.
        let head = tian_head();
        let p = Vector3::new(0.0, 0.0, 60.0);
        let n = tilted(10.0, 90.0); // tilt about x
        let shape = Shape::Cylinder {
            radius: 500.0,
            axis: Vector3::x(),
        };
        let surf = CurvedSurface::through(p, n, &shape).unwrap();
        let r = readings(&head, &surf);
        let ctx = Context::default();
        let plane = normal::plane(&head, &r, &ctx, Method::LeastSquares).unwrap();
        let err = angle_deg(&plane.normal, &n);
        let rho = 45.0 - 60.0 * 25f64.to_radians().tan();
        let first =
            (rho * 25f64.to_radians().tan() * 10f64.to_radians().tan() / 500.0).to_degrees();
        assert_relative_eq!(first, 0.160, epsilon = 0.001);
        assert_relative_eq!(err, 0.1922, epsilon = 0.0005);
        let m = measure(&head, &r, &ctx, Method::LeastSquares, &shape).unwrap();
        assert!(angle_deg(&m.fit.normal, &n) < 1e-9);
    }

    #[test]
    fn plane_shape_is_todays_measurement() {
        let head = tian_head();
        let p = crate::geometry::Plane::through(Vector3::new(0.0, 0.0, 60.0), tilted(7.0, 200.0))
            .unwrap();
        let r: [Option<f64>; 4] = core::array::from_fn(|i| {
            Some(crate::model::distance(&head.sensors[i], &p, i).unwrap() + 0.01 * i as f64)
        });
        let ctx = Context::default();
        for method in [Method::Chen, Method::LeastSquares] {
            let want = normal::measure(&head, &r, &ctx, method).unwrap();
            let got = measure(&head, &r, &ctx, method, &Shape::Plane).unwrap();
            assert_eq!(got.fit.plane, want.plane);
            assert_eq!(got.fit.normal, want.plane.normal);
            assert_eq!(got.deviation, want.deviation);
            assert_eq!(got.attitude, want.attitude);
            assert_eq!(got.fit.iterations, 0);
            // the axis point lies on the fitted plane
            let c = want.plane.centroid;
            assert_relative_eq!(
                want.plane.normal.dot(&(got.fit.point - c)),
                0.0,
                epsilon = 1e-9
            );
        }
    }

    #[test]
    fn three_spots_fit_exactly() {
        let head = tian_head();
        let p = Vector3::new(0.0, 0.0, 55.0);
        let n = tilted(6.0, -40.0);
        let ctx = Context::default();
        for shape in shapes(400.0) {
            let surf = CurvedSurface::through(p, n, &shape).unwrap();
            let full = readings(&head, &surf);
            for missing in 0..4 {
                let mut r = full;
                r[missing] = None;
                let m = measure(&head, &r, &ctx, Method::LeastSquares, &surf.shape()).unwrap();
                assert!(m.fit.plane.degraded);
                assert_relative_eq!(m.fit.normal, n, epsilon = 1e-9);
                assert!(m.fit.rms < 1e-9);
            }
        }
    }

    #[test]
    fn f32_matches_f64() {
        let head = tian_head();
        let h32 = head.cast::<f32>();
        let p = Vector3::new(0.0, 0.0, 60.0);
        let n = tilted(10.0, 120.0);
        let ctx = Context::default();
        for r0 in [300.0, 5000.0] {
            for shape in shapes(r0) {
                let surf = CurvedSurface::through(p, n, &shape).unwrap();
                let r = readings(&head, &surf);
                let r32 = r.map(|x| x.map(|v| v as f32));
                let shape = surf.shape();
                let s32 = shape.cast::<f32>();
                let m =
                    measure(&h32, &r32, &Context::default(), Method::LeastSquares, &s32).unwrap();
                let got: Vector3<f64> = m.fit.normal.cast();
                assert!(
                    angle_deg(&got, &n) < 1e-3,
                    "{shape:?}: {}",
                    angle_deg(&got, &n)
                );
                let m64 = measure(&head, &r, &ctx, Method::LeastSquares, &shape).unwrap();
                assert_relative_eq!(m.fit.point.z as f64, m64.fit.point.z, epsilon = 1e-3);
            }
        }
    }

    /// The stopping rule (module docs, step 3): the `f32` fit, which stops
    /// once `CONTRACTION·δ²` is below its tolerance (one step from the
    /// plane start under moderate tilt), gives the normal of the fully
    /// converged `f64` fit to within `f32` rounding, over both signs,
    /// spheres and cylinders, 300-5000 mm, tilts 0-12° and reading noise up
    /// to ±0.05 mm; under ≤ 4° of tilt it takes one step.
    #[test]
    fn one_step_is_converged() {
        let head = tian_head();
        let h32 = head.cast::<f32>();
        let ctx = Context::default();
        let (mut worst, mut one, mut all) = (0.0f64, 0usize, 0usize);
        for r0 in [300.0, 1000.0, 5000.0] {
            for (si, shape) in shapes(r0).iter().enumerate() {
                for k in 0..60usize {
                    let tilt = (k % 13) as f64;
                    let n = tilted(tilt, k as f64 * 47.0);
                    let p = Vector3::new(0.0, 0.0, 52.0 + (k % 7) as f64);
                    let surf = CurvedSurface::through(p, n, shape).unwrap();
                    let mut r = readings(&head, &surf);
                    for (i, x) in r.iter_mut().enumerate() {
                        let u = ((k * 7 + i * 13 + si * 5) % 11) as f64 - 5.0;
                        *x = x.map(|d| d + u * 0.01);
                    }
                    let s32 = shape.cast::<f32>();
                    let r32 = r.map(|x| x.map(|v| v as f32));
                    let f =
                        fit(&h32, &r32, &Context::default(), Method::LeastSquares, &s32).unwrap();
                    let g = fit(&head, &r, &ctx, Method::LeastSquares, shape).unwrap();
                    worst = worst.max(angle_deg(&f.normal.cast(), &g.normal));
                    if tilt <= 4.0 {
                        all += 1;
                        one += usize::from(f.iterations == 1);
                    }
                }
            }
        }
        assert!(worst < 1e-4, "f32 one-step vs f64 converged: {worst:.2e}°");
        assert_eq!(one, all, "one step under 4° of tilt");
    }

    #[test]
    fn bad_shapes_are_errors() {
        let head = tian_head();
        let surf = CurvedSurface::through(
            Vector3::new(0.0, 0.0, 60.0),
            tilted(3.0, 0.0),
            &shapes(500.0)[0],
        )
        .unwrap();
        let r = readings(&head, &surf);
        let ctx = Context::default();
        let lsq = Method::LeastSquares;
        let go = |s: Shape<f64>| measure(&head, &r, &ctx, lsq, &s).map(|_| ());
        assert_eq!(
            go(Shape::Sphere { radius: 0.0 }),
            Err(Error::OutOfRange("surface radius"))
        );
        assert_eq!(
            go(Shape::Sphere { radius: f64::NAN }),
            Err(Error::NonFinite("surface radius"))
        );
        // spots ~17 mm from their centroid: a 30 mm radius is too small
        assert_eq!(
            go(Shape::Sphere { radius: 30.0 }),
            Err(Error::SurfaceTooCurved)
        );
        assert_eq!(
            go(Shape::Cylinder {
                radius: 500.0,
                axis: Vector3::zeros()
            }),
            Err(Error::ZeroLength("cylinder axis"))
        );
        assert_eq!(
            go(Shape::Cylinder {
                radius: 500.0,
                axis: Vector3::new(0.1, 0.0, 1.0)
            }),
            Err(Error::OutOfRange("cylinder axis along the normal"))
        );
        // too few readings, as for the plane
        let r2 = [r[0], None, r[2], None];
        assert_eq!(
            measure(&head, &r2, &ctx, lsq, &shapes(500.0)[0]).map(|_| ()),
            Err(Error::TooFewReadings(2))
        );
    }

    #[test]
    fn axis_missing_the_surface_is_an_error() {
        // A 30 mm sphere centred 60 mm off the axis: the axis passes beside it.
        let c = Curved {
            s: 1.0,
            r: 30.0,
            axis: None,
        };
        let p0 = Vector3::new(60.0, 0.0, 60.0);
        assert_eq!(
            intersect_axis(&c, &p0, &-Vector3::z()),
            Err(Error::AxisMissesSurface)
        );
        // A cylinder along the spindle axis.
        let c = Curved {
            s: 1.0,
            r: 500.0,
            axis: Some(Vector3::z()),
        };
        assert_eq!(
            intersect_axis(&c, &p0, &-Vector3::x()),
            Err(Error::AxisMissesSurface)
        );
        let s = CurvedSurface {
            centre: Vector3::new(60.0, 0.0, 90.0),
            radius: 30.0,
            axis: None,
        };
        assert_eq!(s.axis_point(), Err(Error::AxisMissesSurface));
        let sensor = crate::head::Sensor::new(Vector3::zeros(), Vector3::z()).unwrap();
        assert_eq!(s.distance(&sensor, 2), Err(Error::BeamMissesSurface(2)));
    }

    #[test]
    fn runaway_step_is_no_convergence() {
        // Spots on a 500 mm sphere, but a start whose normal lies in the
        // micro-plane: the first step would turn it by far more than 30°.
        let head = tian_head();
        let shape = shapes(500.0)[0];
        let surf =
            CurvedSurface::through(Vector3::new(0.0, 0.0, 60.0), tilted(2.0, 0.0), &shape).unwrap();
        let r = readings(&head, &surf);
        let (plane, spots) =
            crate::normal::plane_and_spots(&head, &r, &Context::default(), Method::LeastSquares)
                .unwrap();
        let pts: [Vector3<f64>; 4] = core::array::from_fn(|i| spots[i].unwrap() - plane.centroid);
        let pb = Problem {
            c: Curved::new(&shape).unwrap().unwrap(),
            m: plane.centroid,
            g: plane.normal,
            pts: &pts,
        };
        let mut st = State {
            h: 0.0,
            n: Vector3::new(0.0, 0.6, -0.8),
        };
        assert_eq!(gauss_newton(&pb, &mut st, 400.0), Err(Error::NoConvergence));
    }

    #[test]
    fn radius_error_leaves_a_proportional_bias() {
        // Error model: a radius off by ΔR leaves ≈ ε_plane·|ΔR|/R_used.
        let head = tian_head();
        let n = tilted(10.0, 90.0);
        let truth = CurvedSurface::through(
            Vector3::new(0.0, 0.0, 60.0),
            n,
            &Shape::Sphere { radius: 500.0 },
        )
        .unwrap();
        let r = readings(&head, &truth);
        let ctx = Context::default();
        let lsq = Method::LeastSquares;
        let plane = angle_deg(&normal::plane(&head, &r, &ctx, lsq).unwrap().normal, &n);
        let used = Shape::Sphere { radius: 550.0 };
        let got = angle_deg(
            &measure(&head, &r, &ctx, lsq, &used).unwrap().fit.normal,
            &n,
        );
        let want = plane * 50.0 / 550.0;
        assert_relative_eq!(got, want, max_relative = 0.1);
    }

    #[test]
    fn cylinder_axis_elevation_is_free() {
        // The head tilted 8° along the cylinder's axis: an axis taken from the
        // nominal pose (perpendicular to the spindle) is 8° out of the
        // tangent plane; only its azimuth is used, so the fit stays exact to
        // second order.
        let head = tian_head();
        let n = tilted(8.0, 0.0);
        let truth = CurvedSurface::through(
            Vector3::new(0.0, 0.0, 60.0),
            n,
            &Shape::Cylinder {
                radius: 400.0,
                axis: Vector3::x(),
            },
        )
        .unwrap();
        let r = readings(&head, &truth);
        let nominal = Shape::Cylinder {
            radius: 400.0,
            axis: Vector3::x(),
        };
        let m = measure(
            &head,
            &r,
            &Context::default(),
            Method::LeastSquares,
            &nominal,
        )
        .unwrap();
        assert!(
            angle_deg(&m.fit.normal, &n) < 0.002,
            "{}",
            angle_deg(&m.fit.normal, &n)
        );
    }
}

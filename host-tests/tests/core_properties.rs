//! Property tests of the measurement core (issue 2): invariance under rigid
//! motions, exact recovery from noiseless readings, Tian's direct formula
//! against the normal-based angles, Euler and attitude round trips, f32 vs
//! f64, and errors instead of NaN for bad input.
#![allow(missing_docs, clippy::unwrap_used)]

use approx::assert_relative_eq;
use nalgebra::{Rotation3, Unit, Vector3};
use perpend_core::angles::{
    euler_solutions, tian_direct, Attitude, Deviation, Euler, EulerSolutions,
};
use perpend_core::ext::Context;
use perpend_core::geometry::Plane;
use perpend_core::head::{Head4, Sensor};
use perpend_core::model::distance;
use perpend_core::normal::{measure, plane, Method};
use perpend_core::Error;
use proptest::prelude::*;

/// A cone head with the paper's error sizes (±1.5 mm, ±0.07 rad).
fn head_strategy() -> impl Strategy<Value = Head4<f64>> {
    (
        50.0..70.0f64,
        20.0..30.0f64,
        prop::array::uniform4((
            prop::array::uniform3(-1.5..1.5f64),
            prop::array::uniform3(-0.07..0.07f64),
        )),
    )
        .prop_map(|(r, lam, errs)| {
            let mut h = Head4::cone(r, lam.to_radians(), -30.0, 0.0).unwrap();
            for (s, (dp, dd)) in h.sensors.iter_mut().zip(errs) {
                *s = Sensor::new(s.zero + Vector3::from(dp), s.dir + Vector3::from(dd)).unwrap();
            }
            h
        })
}

/// A plane in front of the head: tilted up to 20° from the spindle axis,
/// crossing the axis at z = 10..30 mm, i.e. 40..60 mm from the zero points
/// (at z = −30) and before the beams of any head of [`head_strategy`] meet
/// (≥ 86 mm from the zero points).
fn plane_strategy() -> impl Strategy<Value = Plane<f64>> {
    (0.0..20.0f64, 0.0..360.0f64, 10.0..30.0f64).prop_map(|(tilt, az, z0)| {
        let (t, a) = (tilt.to_radians(), az.to_radians());
        let n = Vector3::new(t.sin() * a.cos(), t.sin() * a.sin(), t.cos());
        Plane::through(Vector3::new(0.0, 0.0, z0), n).unwrap()
    })
}

fn rigid_strategy() -> impl Strategy<Value = (Rotation3<f64>, Vector3<f64>)> {
    (
        prop::array::uniform3(-1.0..1.0f64),
        -3.0..3.0f64,
        prop::array::uniform3(-100.0..100.0f64),
    )
        .prop_filter("axis", |(ax, _, _)| Vector3::from(*ax).norm() > 1e-3)
        .prop_map(|(ax, ang, t)| {
            (
                Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::from(ax)), ang),
                Vector3::from(t),
            )
        })
}

fn readings(head: &Head4<f64>, p: &Plane<f64>) -> Option<[Option<f64>; 4]> {
    let mut r = [None; 4];
    for (i, (ri, s)) in r.iter_mut().zip(&head.sensors).enumerate() {
        *ri = Some(distance(s, p, i).ok()?);
    }
    Some(r)
}

fn moved(head: &Head4<f64>, rot: &Rotation3<f64>, t: &Vector3<f64>) -> Head4<f64> {
    let mut h = *head;
    for s in h.sensors.iter_mut() {
        *s = Sensor::new(rot * s.zero + t, rot * s.dir).unwrap();
    }
    h
}

fn angle(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Noiseless readings give the plane's normal exactly (towards the head).
    #[test]
    fn exact_recovery(head in head_strategy(), p in plane_strategy()) {
        let r = readings(&head, &p).unwrap();
        for m in [Method::Chen, Method::LeastSquares] {
            let f = plane(&head, &r, &Context::default(), m).unwrap();
            prop_assert!(angle(&f.normal, &(-p.n)) < 1e-10);
            prop_assert!(f.rms < 1e-9);
        }
    }

    /// Moving head and plane together by any rigid motion leaves the
    /// readings unchanged and rotates the normal with them.
    #[test]
    fn normal_equivariant_under_rigid_motion(
        head in head_strategy(), p in plane_strategy(), (rot, t) in rigid_strategy()
    ) {
        let r = readings(&head, &p).unwrap();
        let head2 = moved(&head, &rot, &t);
        let p2 = p.transformed(rot.matrix(), &t);
        let r2 = readings(&head2, &p2).unwrap();
        for i in 0..4 {
            prop_assert!((r[i].unwrap() - r2[i].unwrap()).abs() < 1e-9);
        }
        // noisy-ish readings (a fixed perturbation) to exercise non-exact fits
        let rn = [r[0].map(|x| x + 0.01), r[1], r[2].map(|x| x - 0.02), r[3]];
        for m in [Method::Chen, Method::LeastSquares] {
            let a = plane(&head, &rn, &Context::default(), m).unwrap();
            let b = plane(&head2, &rn, &Context::default(), m).unwrap();
            prop_assert!(angle(&(rot * a.normal), &b.normal) < 1e-10);
            prop_assert!((a.rms - b.rms).abs() < 1e-9);
        }
    }

    /// θ is invariant under translations and rotations about the spindle
    /// axis; θ1/θ2 rotate as the axes do (a quarter turn maps θ1 → θ2 with
    /// the sign the axis mapping gives).
    #[test]
    fn deviation_invariant_about_spindle(
        head in head_strategy(), p in plane_strategy(),
        ang in -3.0..3.0f64, t in prop::array::uniform3(-20.0..20.0f64)
    ) {
        let rot = Rotation3::from_axis_angle(&Vector3::z_axis(), ang);
        let t = Vector3::from(t);
        let r = readings(&head, &p).unwrap();
        let a = measure(&head, &r, &Context::default(), Method::LeastSquares).unwrap();
        let head2 = moved(&head, &rot, &t);
        let b = measure(&head2, &r, &Context::default(), Method::LeastSquares).unwrap();
        prop_assert!((a.deviation.theta - b.deviation.theta).abs() < 1e-10);
        // quarter turn: n' = Rz(90°) n = (−n_y, n_x, n_z) → θ2' = atan2(n_y, −n_z) = θ1
        let q = Rotation3::from_axis_angle(&Vector3::z_axis(), core::f64::consts::FRAC_PI_2);
        let d1 = Deviation::from_normal(&a.plane.normal).unwrap();
        let d2 = Deviation::from_normal(&(q * a.plane.normal)).unwrap();
        prop_assert!((d2.theta2 - d1.theta1).abs() < 1e-12);
        prop_assert!((d2.theta1 + d1.theta2).abs() < 1e-12);
    }

    /// Tian's direct formula (eq. 10-12) equals the normal-based angles
    /// (eq. 1-5) for an ideal cone head.
    #[test]
    fn tian_direct_matches_normal(
        r0 in 50.0..70.0f64, lam in 10.0..30.0f64, p in plane_strategy()
    ) {
        let lam = lam.to_radians();
        let head = Head4::cone(r0, lam, -30.0, 0.0).unwrap();
        let r = readings(&head, &p).unwrap();
        let m = measure(&head, &r, &Context::default(), Method::LeastSquares).unwrap();
        // our sensors +x, +y, −x, −y are Tian's P4, P2, P3, P1
        let h = [r[3].unwrap(), r[1].unwrap(), r[2].unwrap(), r[0].unwrap()];
        let t = tian_direct(h, lam, 2.0 * r0, 2.0 * r0).unwrap();
        prop_assert!((t.theta1 - m.deviation.theta1).abs() < 1e-10);
        prop_assert!((t.theta2 - m.deviation.theta2).abs() < 1e-10);
        prop_assert!((t.theta - m.deviation.theta).abs() < 1e-10);
        prop_assert!((t.t1 - m.deviation.t1).abs() < 1e-10);
    }

    /// Euler ZYX: matrix → solutions → matrix, and the cos b > 0 solution
    /// returns the input angles.
    #[test]
    fn euler_round_trip(a in -3.1..3.1f64, b in -1.55..1.55f64, c in -3.1..3.1f64) {
        let e = Euler { a, b, c };
        match euler_solutions(&e.matrix()).unwrap() {
            EulerSolutions::Regular(s) => {
                prop_assert!((s[0].a - a).abs() < 1e-8);
                prop_assert!((s[0].b - b).abs() < 1e-8);
                prop_assert!((s[0].c - c).abs() < 1e-8);
                for x in s {
                    prop_assert!((x.matrix() - e.matrix()).abs().max() < 1e-9);
                }
                prop_assert!(s[1].b.cos() < 0.0);
            }
            EulerSolutions::Degenerate { particular, .. } => {
                prop_assert!((particular.matrix() - e.matrix()).abs().max() < 1e-6);
            }
        }
    }

    /// The attitude correction turns the spindle onto the inward normal.
    #[test]
    fn attitude_round_trip(p in plane_strategy()) {
        let n = -p.n;
        let att = Attitude::from_normal(&n).unwrap();
        let f = att.rotation() * Vector3::z();
        prop_assert!((f + n).norm() < 1e-12);
    }

    /// The board's f32 path agrees with the host's f64 path to far below the
    /// sensors' noise floor (0.001°).
    #[test]
    fn f32_agrees_with_f64(head in head_strategy(), p in plane_strategy()) {
        let r = readings(&head, &p).unwrap();
        let a = measure(&head, &r, &Context::default(), Method::LeastSquares).unwrap();
        let h32 = head.cast::<f32>();
        let r32 = r.map(|x| x.map(|v| v as f32));
        for m in [Method::Chen, Method::LeastSquares] {
            let b = measure(&h32, &r32, &Context::default(), m).unwrap();
            let nb = Vector3::new(b.plane.normal.x as f64, b.plane.normal.y as f64, b.plane.normal.z as f64);
            prop_assert!(angle(&a.plane.normal, &nb).to_degrees() < 1e-3);
            prop_assert!((b.deviation.theta1 as f64 - a.deviation.theta1).abs().to_degrees() < 1e-3);
        }
    }

    /// Any finite readings give finite results or a documented error, never
    /// a NaN.
    #[test]
    fn never_nan(head in head_strategy(), r in prop::array::uniform4(prop::option::of(0.0..200.0f64))) {
        for m in [Method::Chen, Method::LeastSquares] {
            match measure(&head, &r, &Context::default(), m) {
                Ok(x) => {
                    prop_assert!(x.plane.normal.iter().all(|v| v.is_finite()));
                    prop_assert!(x.deviation.theta.is_finite() && x.attitude.pitch.is_finite());
                    prop_assert!(x.plane.rms.is_finite());
                }
                Err(e) => prop_assert!(matches!(
                    e,
                    Error::TooFewReadings(_) | Error::DegenerateSpots | Error::SurfaceFacesAway
                )),
            }
        }
    }
}

#[test]
fn bad_inputs_give_documented_errors() {
    let head = Head4::cone(50.0, 0.5, 0.0, 0.0).unwrap();
    let ctx = Context::default();
    assert_eq!(
        measure(
            &head,
            &[Some(f64::NAN), Some(1.0), Some(1.0), Some(1.0)],
            &ctx,
            Method::Chen
        ),
        Err(Error::NonFinite("reading"))
    );
    assert_eq!(
        measure(
            &head,
            &[Some(1.0), Some(-0.5), Some(1.0), Some(1.0)],
            &ctx,
            Method::Chen
        ),
        Err(Error::NegativeDistance(1))
    );
    assert_eq!(
        Sensor::new(Vector3::new(0.0, f64::INFINITY, 0.0), Vector3::z()),
        Err(Error::NonFinite("zero point"))
    );
    assert_eq!(
        Sensor::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 1e-30)),
        Err(Error::ZeroLength("beam direction"))
    );
    // beam parallel to the plane
    let s = Sensor::new(Vector3::zeros(), Vector3::x()).unwrap();
    let p = Plane::from_abcd(0.0, 0.0, 1.0, -40.0).unwrap();
    assert_eq!(distance(&s, &p, 0), Err(Error::BeamParallelToPlane(0)));
    assert_eq!(
        tian_direct([1.0, f64::NAN, 1.0, 1.0], 0.5, 100.0, 100.0),
        Err(Error::NonFinite("reading"))
    );
}

#[test]
fn golden_chen_table2_head_normal() {
    // Chen Table 2 head (true parameters) on the Table 1 plane, in the
    // paper's own frame (beams along −z): the normal of the plane is found
    // back exactly and oriented towards the head (+z side here).
    let t2 = [
        ([51.3, 0.9, 1.1], [-0.4555, 0.0506, -0.8888]),
        ([1.3, 48.6, 1.6], [-0.0634, -0.4521, -0.8897]),
        ([-48.7, -1.2, 1.2], [0.4493, -0.0365, -0.8926]),
        ([1.5, -48.9, 1.4], [0.0339, 0.4318, -0.9013]),
    ];
    let head =
        Head4::new(t2.map(|(e, u)| Sensor::new(Vector3::from(e), Vector3::from(u)).unwrap()));
    let p = Plane::from_abcd(0.0173, -0.3071, 0.9515, 34.1218).unwrap();
    let r = readings(&head, &p).unwrap();
    let f = plane(&head, &r, &Context::default(), Method::Chen).unwrap();
    assert_relative_eq!(f.normal, p.n, epsilon = 1e-12);
    // hand check of sensor 1's reading: d = -(n·E + D)/(n·u)
    let u = Vector3::new(-0.4555, 0.0506, -0.8888).normalize();
    let e = Vector3::new(51.3, 0.9, 1.1);
    let want = -(p.n.dot(&e) + p.d) / p.n.dot(&u);
    assert_relative_eq!(r[0].unwrap(), want, epsilon = 1e-12);
}

//! Property tests of the curved-surface normal (issue 14, item 1,
//! `perpend_core::surface`): exact recovery on spheres and cylinders of
//! either sign for heads with the paper's error sizes, invariance under a
//! roll about the spindle axis, the plane as the limit of a large radius,
//! f32 against f64, and errors instead of NaN for any input.
#![allow(missing_docs, clippy::unwrap_used)]

use nalgebra::{Rotation3, Vector3};
use perpend_core::ext::Context;
use perpend_core::head::{Head4, Sensor};
use perpend_core::normal::{plane, Method};
use perpend_core::surface::{measure, CurvedSurface, Shape};
use proptest::prelude::*;

/// A Tian-style cone head (40-50 mm circle, 20-30°) with the paper's error
/// sizes (±1.5 mm, ±0.07 rad).
fn head_strategy() -> impl Strategy<Value = Head4<f64>> {
    (
        40.0..50.0f64,
        20.0..30.0f64,
        prop::array::uniform4((
            prop::array::uniform3(-1.5..1.5f64),
            prop::array::uniform3(-0.07..0.07f64),
        )),
    )
        .prop_map(|(r, lam, errs)| {
            let mut h = Head4::cone(r, lam.to_radians(), 0.0, 0.0).unwrap();
            for (s, (dp, dd)) in h.sensors.iter_mut().zip(errs) {
                *s = Sensor::new(s.zero + Vector3::from(dp), s.dir + Vector3::from(dd)).unwrap();
            }
            h
        })
}

/// A sphere or cylinder (signed radius 250..20000 mm, axis in the tangent
/// plane at a random azimuth) through the spindle axis at z = 45..60 mm,
/// its normal tilted up to 15°.
fn surface_strategy() -> impl Strategy<Value = CurvedSurface<f64>> {
    (
        250.0..20000.0f64,
        any::<bool>(),
        any::<bool>(),
        0.0..15.0f64,
        0.0..360.0f64,
        0.0..180.0f64,
        45.0..60.0f64,
    )
        .prop_map(|(r, concave, cyl, tilt, az, psi, z)| {
            let (t, a) = (tilt.to_radians(), az.to_radians());
            let n = Vector3::new(t.sin() * a.cos(), t.sin() * a.sin(), -t.cos());
            let radius = if concave { -r } else { r };
            let shape = if cyl {
                let (p, q) = (psi.to_radians().cos(), psi.to_radians().sin());
                Shape::Cylinder {
                    radius,
                    axis: Vector3::new(p, q, 0.0),
                }
            } else {
                Shape::Sphere { radius }
            };
            CurvedSurface::through(Vector3::new(0.0, 0.0, z), n, &shape).unwrap()
        })
}

fn readings(head: &Head4<f64>, s: &CurvedSurface<f64>) -> Option<[Option<f64>; 4]> {
    let mut r = [None; 4];
    for (i, (ri, sensor)) in r.iter_mut().zip(&head.sensors).enumerate() {
        *ri = Some(s.distance(sensor, i).ok()?);
    }
    Some(r)
}

fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

fn shape32(s: &Shape<f64>) -> Shape<f32> {
    match *s {
        Shape::Plane => Shape::Plane,
        Shape::Sphere { radius } => Shape::Sphere {
            radius: radius as f32,
        },
        Shape::Cylinder { radius, axis } => Shape::Cylinder {
            radius: radius as f32,
            axis: axis.cast(),
        },
    }
}

const LSQ: Method = Method::LeastSquares;

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Noise-free readings of the nominal shape give the true normal at
    /// the axis point, with a zero residual, whatever the head's errors.
    #[test]
    fn exact_recovery(head in head_strategy(), s in surface_strategy()) {
        let r = readings(&head, &s).unwrap();
        let (p, n) = s.axis_point().unwrap();
        let m = measure(&head, &r, &Context::default(), LSQ, &s.shape()).unwrap();
        prop_assert!(angle_deg(&m.fit.normal, &n) < 1e-7, "{}", angle_deg(&m.fit.normal, &n));
        prop_assert!((m.fit.point - p).norm() < 1e-6);
        prop_assert!(m.fit.rms < 1e-7);
        prop_assert!(m.fit.iterations <= 8);
    }

    /// Rolling head and surface together about the spindle axis rolls the
    /// normal and leaves θ, the residual and the axis point alone.
    #[test]
    fn roll_invariance(head in head_strategy(), s in surface_strategy(), roll in -3.1..3.1f64,
                       noise in prop::array::uniform4(-0.01..0.01f64)) {
        let rot = Rotation3::from_axis_angle(&Vector3::z_axis(), roll);
        let mut moved = head;
        for x in moved.sensors.iter_mut() {
            *x = Sensor::new(rot * x.zero, rot * x.dir).unwrap();
        }
        let s2 = s.transformed(rot.matrix(), &Vector3::zeros());
        let mut r = readings(&head, &s).unwrap();
        for (x, e) in r.iter_mut().zip(noise) {
            *x = x.map(|d| d + e);
        }
        let ctx = Context::default();
        let a = measure(&head, &r, &ctx, LSQ, &s.shape()).unwrap();
        let b = measure(&moved, &r, &ctx, LSQ, &s2.shape()).unwrap();
        prop_assert!(angle_deg(&(rot * a.fit.normal), &b.fit.normal) < 1e-9);
        prop_assert!((a.deviation.theta - b.deviation.theta).abs() < 1e-10);
        prop_assert!((a.fit.rms - b.fit.rms).abs() < 1e-9);
        prop_assert!((a.fit.point.z - b.fit.point.z).abs() < 1e-8);
    }

    /// A plane is a sphere of infinite radius: on a plane's readings a
    /// radius of 10⁷ mm gives the plane's normal.
    #[test]
    fn large_radius_is_the_plane(head in head_strategy(), tilt in 0.0..15.0f64, az in 0.0..6.3f64) {
        let t = tilt.to_radians();
        let n = Vector3::new(t.sin() * az.cos(), t.sin() * az.sin(), -t.cos());
        let p = perpend_core::geometry::Plane::through(Vector3::new(0.0, 0.0, 55.0), n).unwrap();
        let r: [Option<f64>; 4] = core::array::from_fn(|i| {
            Some(perpend_core::model::distance(&head.sensors[i], &p, i).unwrap())
        });
        let ctx = Context::default();
        let flat = plane(&head, &r, &ctx, LSQ).unwrap();
        for shape in [Shape::Sphere { radius: 1e7 }, Shape::Sphere { radius: -1e7 },
                      Shape::Cylinder { radius: 1e7, axis: Vector3::y() }] {
            let m = measure(&head, &r, &ctx, LSQ, &shape).unwrap();
            prop_assert!(angle_deg(&m.fit.normal, &flat.normal) < 1e-4);
        }
    }

    /// The board's f32 agrees with the host's f64 to < 0.001° on noisy
    /// readings.
    #[test]
    fn f32_matches_f64(head in head_strategy(), s in surface_strategy(),
                       noise in prop::array::uniform4(-0.02..0.02f64)) {
        let mut r = readings(&head, &s).unwrap();
        for (x, e) in r.iter_mut().zip(noise) {
            *x = x.map(|d| d + e);
        }
        let ctx = Context::default();
        let m64 = measure(&head, &r, &ctx, LSQ, &s.shape()).unwrap();
        let r32 = r.map(|x| x.map(|d| d as f32));
        let m32 = measure(&head.cast::<f32>(), &r32, &Context::default(), LSQ, &shape32(&s.shape()))
            .unwrap();
        let n32: Vector3<f64> = m32.fit.normal.cast();
        prop_assert!(angle_deg(&n32, &m64.fit.normal) < 1e-3, "{}", angle_deg(&n32, &m64.fit.normal));
        prop_assert!((m32.deviation.theta as f64 - m64.deviation.theta).abs().to_degrees() < 1e-3);
    }

    /// Any readings and any shape: a finite unit normal and finite angles,
    /// or an error; never a NaN, never a panic.
    #[test]
    fn never_nan(head in head_strategy(),
                 r in prop::array::uniform4(prop::option::of(prop_oneof![
                     0.0..200.0f64, Just(f64::NAN), Just(f64::INFINITY), Just(-1.0)])),
                 radius in prop_oneof![-1e9..1e9f64, Just(0.0), Just(f64::NAN), -50.0..50.0f64],
                 axis in prop::array::uniform3(prop_oneof![-1.0..1.0f64, Just(0.0), Just(f64::NAN)]),
                 cyl in any::<bool>()) {
        let shape = if cyl {
            Shape::Cylinder { radius, axis: Vector3::from(axis) }
        } else {
            Shape::Sphere { radius }
        };
        for h in [&head] {
            if let Ok(m) = measure(h, &r, &Context::default(), LSQ, &shape) {
                prop_assert!((m.fit.normal.norm() - 1.0).abs() < 1e-9);
                prop_assert!(m.fit.normal.z < 0.0);
                for v in [m.deviation.theta, m.deviation.theta1, m.deviation.theta2,
                          m.attitude.pitch, m.attitude.yaw, m.fit.rms, m.fit.point.z] {
                    prop_assert!(v.is_finite());
                }
            }
            let r32 = r.map(|x| x.map(|d| d as f32));
            if let Ok(m) = measure(&h.cast::<f32>(), &r32, &Context::default(), LSQ, &shape32(&shape)) {
                prop_assert!(m.fit.normal.iter().all(|x| x.is_finite()));
                prop_assert!(m.deviation.theta.is_finite() && m.fit.rms.is_finite());
            }
        }
    }
}

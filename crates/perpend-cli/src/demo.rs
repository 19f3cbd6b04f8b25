//! `perpend demo`: an ideal cone head looks at a plane; print the readings,
//! the spots, the micro-plane normal (both methods), Tian's deviation angles
//! (from the normal and from his direct formula, eq. 10-12) and Chen's
//! attitude correction (eq. 22).

use anyhow::{bail, Context as _, Result};
use nalgebra::Vector3;
use perpend_core::angles::{tian_direct, Deviation};
use perpend_core::ext::Context;
use perpend_core::geometry::Plane;
use perpend_core::head::Head4;
use perpend_core::model::distance;
use perpend_core::normal::{measure, Method};

/// Arguments of `perpend demo`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Plane `a·x + b·y + c·z + d = 0` in the TCS (+z = spindle feed), as
    /// `A,B,C,D`.
    #[arg(long, default_value = "0.035,-0.052,1,-40", allow_hyphen_values = true)]
    pub plane: String,
    /// Radius of the circle of zero points [mm].
    #[arg(long, default_value_t = 50.0)]
    pub radius_mm: f64,
    /// Cone half-angle between each beam and the spindle axis [deg].
    #[arg(long, default_value_t = 30.0)]
    pub lambda_deg: f64,
    /// Drop this sensor's reading (1-based) to show three-sensor operation.
    #[arg(long)]
    pub drop: Option<usize>,
}

/// Parses `A,B,C,D` into a plane.
pub fn parse_plane(s: &str) -> Result<Plane<f64>> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("plane '{s}': expected four numbers A,B,C,D"))?;
    if v.len() != 4 {
        bail!(
            "plane '{s}': expected four numbers A,B,C,D, got {}",
            v.len()
        );
    }
    Plane::from_abcd(v[0], v[1], v[2], v[3]).map_err(|e| anyhow::anyhow!("plane '{s}': {e}"))
}

/// Runs the demo and prints the report.
pub fn run(a: &Args) -> Result<()> {
    let plane = parse_plane(&a.plane)?;
    let lambda = a.lambda_deg.to_radians();
    let head = Head4::cone(a.radius_mm, lambda, 0.0, 0.0)?;
    let mut readings = [None; 4];
    for (i, r) in readings.iter_mut().enumerate() {
        *r = Some(distance(&head.sensors[i], &plane, i)?);
    }
    if let Some(k) = a.drop {
        if !(1..=4).contains(&k) {
            bail!("--drop {k}: sensors are numbered 1..4");
        }
        readings[k - 1] = None;
    }
    println!(
        "head: ideal cone, r = {} mm, λ = {}°, sensors at +x, +y, −x, −y (1..4)",
        a.radius_mm, a.lambda_deg
    );
    println!(
        "plane: n = ({:.6}, {:.6}, {:.6}), d = {:.4} mm",
        plane.n.x, plane.n.y, plane.n.z, plane.d
    );
    for (i, r) in readings.iter().enumerate() {
        match r {
            Some(d) => {
                let s = head.sensors[i].spot(*d);
                println!(
                    "  sensor {}: d = {:9.4} mm  spot = ({:8.3}, {:8.3}, {:8.3})",
                    i + 1,
                    d,
                    s.x,
                    s.y,
                    s.z
                );
            }
            None => println!("  sensor {}: no reading", i + 1),
        }
    }
    let truth = Deviation::from_normal(&(-plane.n))?;
    for method in [Method::Chen, Method::LeastSquares] {
        let m = measure(&head, &readings, &Context::default(), method)?;
        let n = m.plane.normal;
        println!("{method:?}:");
        println!(
            "  normal (towards head) = ({:.6}, {:.6}, {:.6}){}",
            n.x,
            n.y,
            n.z,
            if m.plane.degraded {
                "  [degraded: three sensors]"
            } else {
                ""
            }
        );
        println!(
            "  θ1 = {:.4}°  θ2 = {:.4}°  θ = {:.4}°  t1 = {:.4}°",
            m.deviation.theta1.to_degrees(),
            m.deviation.theta2.to_degrees(),
            m.deviation.theta.to_degrees(),
            m.deviation.t1.to_degrees()
        );
        println!(
            "  attitude correction: pitch = {:.4}°  yaw = {:.4}°   plane rms = {:.2e} mm",
            m.attitude.pitch.to_degrees(),
            m.attitude.yaw.to_degrees(),
            m.plane.rms
        );
        let err = angle_deg(&n, &(-plane.n));
        println!("  error vs. the plane's normal: {err:.2e}°");
    }
    if readings.iter().all(Option::is_some) {
        // Tian's P1 (−y), P2 (+y), P3 (−x), P4 (+x) are our 4, 2, 3, 1.
        let h = [readings[3], readings[1], readings[2], readings[0]].map(|r| r.unwrap_or(0.0));
        let l = 2.0 * a.radius_mm;
        let t = tian_direct(h, lambda, l, l)?;
        println!(
            "Tian direct (eq. 10-12): θ1 = {:.4}°  θ2 = {:.4}°  θ = {:.4}°",
            t.theta1.to_degrees(),
            t.theta2.to_degrees(),
            t.theta.to_degrees()
        );
    }
    println!(
        "truth: θ1 = {:.4}°  θ2 = {:.4}°  θ = {:.4}°",
        truth.theta1.to_degrees(),
        truth.theta2.to_degrees(),
        truth.theta.to_degrees()
    );
    Ok(())
}

/// Angle between two vectors [deg].
pub fn angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

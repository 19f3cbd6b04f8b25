//! `perpend plan --reversal N`: the planned poses turned about the spindle
//! axis (issue 36, [`super`]).
//!
//! Choice: **every** planned pose is visited at each of the `N` joint
//! angles `k·360°/N` (N·n poses). That is reversal in the metrological
//! sense — the same datum seen with the head turned — and it keeps the
//! D-optimal spread of the plan at every angle, so the head's parameters
//! are as well determined as by the plan alone while the tracker tilt
//! separates (`perpend bench frames`: 8 turned poses of 90 resolve a
//! 0.05° tilt, 45 reach the floor; 4 × 16 = 64 turned poses do both).
//!
//! The CSV keeps `perpend plan`'s columns, which describe the plane **in
//! the TCS after the turn** (so a reader that ignores the new columns still
//! calibrates correctly), and adds `joint_deg` (the last joint's angle
//! relative to the planned pose) and `base_pose` (which planned pose it
//! turns).

use anyhow::{anyhow, bail, Result};
use perpend_core::geometry::Plane;

use super::FramePose;
use crate::sim::PlannedPose;

/// Most joint angles per pose (every 15°).
pub const MAX_REVERSAL: usize = 24;

/// One row of the turned plan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TurnedPose {
    /// The plane in the TCS after the turn, as tilts and standoff.
    pub pose: PlannedPose,
    /// Last-joint angle [deg].
    pub joint_deg: f64,
    /// The planned pose it turns (1-based).
    pub base_pose: usize,
}

/// Tilts of a plane (Tian's θ1, θ2 of `sim::plane_from_tilts`) and where
/// it crosses the spindle axis.
fn tilts_of(p: &Plane<f64>) -> PlannedPose {
    let n = if p.n.z < 0.0 { p.n } else { -p.n };
    let d = if p.n.z < 0.0 { p.d } else { -p.d };
    PlannedPose {
        tilt_x_deg: n.y.atan2(-n.z).to_degrees(),
        tilt_y_deg: (-n.x).atan2(-n.z).to_degrees(),
        standoff_mm: -d / n.z,
    }
}

/// Every pose of `poses` at `n` joint angles `k·360°/n`, pose by pose.
///
/// # Errors
/// `n` = 0 or above [`MAX_REVERSAL`].
pub fn turned(poses: &[PlannedPose], n: usize) -> Result<Vec<TurnedPose>> {
    if n == 0 || n > MAX_REVERSAL {
        bail!(
            "--reversal {n}: give the number of joint angles per pose, 1 (none) to {MAX_REVERSAL}; 4 turns every pose to 0/90/180/270°"
        );
    }
    let step = 360.0 / n as f64;
    Ok(poses
        .iter()
        .enumerate()
        .flat_map(|(b, p)| {
            (0..n).map(move |k| {
                let joint_deg = step * k as f64;
                let fp = FramePose::turned(&p.plane(), joint_deg.to_radians());
                TurnedPose {
                    pose: tilts_of(&fp.plane),
                    joint_deg,
                    base_pose: b + 1,
                }
            })
        })
        .collect())
}

/// `perpend plan --reversal n`: writes the plan to `path` with every pose
/// at `n` joint angles (module header).
///
/// # Errors
/// A bad `n`, I/O.
pub fn write_reversal(path: &std::path::Path, poses: &[PlannedPose], n: usize) -> Result<()> {
    let rows = turned(poses, n)?;
    let mut s = format!(
        "# perpend plan --reversal {n}: D-optimal datum-plane poses, each at {n} angles of the last joint about the spindle axis; planes in the TCS after the turn (+z along the feed)\n"
    );
    s.push_str("pose,tilt_x_deg,tilt_y_deg,standoff_mm,a,b,c,d_mm,joint_deg,base_pose\n");
    for (k, r) in rows.iter().enumerate() {
        let pl = r.pose.plane();
        s.push_str(&format!(
            "{},{:.4},{:.4},{:.4},{:.9},{:.9},{:.9},{:.6},{:.3},{}\n",
            k + 1,
            r.pose.tilt_x_deg,
            r.pose.tilt_y_deg,
            r.pose.standoff_mm,
            pl.n.x,
            pl.n.y,
            pl.n.z,
            pl.d,
            r.joint_deg,
            r.base_pose
        ));
    }
    std::fs::write(path, s).map_err(|e| anyhow!("{}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turned_poses_keep_the_tilt_and_standoff_and_turn_its_direction() {
        let p = PlannedPose {
            tilt_x_deg: 6.0,
            tilt_y_deg: 0.0,
            standoff_mm: 34.0,
        };
        let t = turned(&[p, p], 4).unwrap();
        assert_eq!(t.len(), 8);
        assert_eq!((t[4].base_pose, t[4].joint_deg), (2, 0.0));
        // at 0° the plan itself; at 180° the opposite tilt; at 90° the tilt
        // moves to the other axis (the head turned, the plate did not)
        assert!((t[0].pose.tilt_x_deg - 6.0).abs() < 1e-9);
        assert!((t[2].pose.tilt_x_deg + 6.0).abs() < 1e-9);
        assert!(
            t[1].pose.tilt_x_deg.abs() < 1e-9 && (t[1].pose.tilt_y_deg.abs() - 6.0).abs() < 1e-9
        );
        for r in &t {
            assert!((r.pose.standoff_mm - 34.0).abs() < 1e-9);
        }
    }

    #[test]
    fn reversal_out_of_range_is_refused_and_written_with_the_joint_column() {
        let p = PlannedPose {
            tilt_x_deg: 1.0,
            tilt_y_deg: -2.0,
            standoff_mm: 30.0,
        };
        let e = turned(&[p], 0).unwrap_err().to_string();
        assert!(
            e.contains("--reversal 0") && e.contains("0/90/180/270"),
            "{e}"
        );
        assert!(turned(&[p], MAX_REVERSAL + 1).is_err());
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("plan.csv");
        write_reversal(&f, &[p], 2).unwrap();
        let s = std::fs::read_to_string(&f).unwrap();
        assert!(
            s.lines().nth(1).unwrap().ends_with("joint_deg,base_pose"),
            "{s}"
        );
        assert_eq!(s.lines().count(), 4);
        assert!(s.lines().nth(3).unwrap().contains(",180.000,1"), "{s}");
    }
}

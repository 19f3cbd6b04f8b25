//! Capture: the controller's "measure now" (command 0x2500 = 1, by SDO or
//! the command RPDO) averages the angles of the next `n` valid samples
//! (0x2501) into 0x2502, so a PLC gets one settled value per robot pose
//! instead of picking single samples out of the TPDO stream.
//!
//! The mean of `n` samples divides the white angle noise by `√n`; it does
//! nothing against errors common to the samples (calibration, the surface
//! itself). Invalid samples (status without a plane, or not
//! [`Output::valid`]) are skipped; a capture that has not found `n` valid
//! samples after `4·n` samples ends with what it has ("samples used" < n,
//! 0 when none: the angles are then NaN), so a pose where the board
//! cannot measure still completes the handshake.

use crate::pipeline::Output;

/// Longest a capture waits, in multiples of its sample count.
pub const PATIENCE: u32 = 4;

/// A capture in progress.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Capture {
    want: u16,
    seen: u32,
    used: u16,
    /// θ1, θ2, θ, pitch, yaw of the first valid sample \[deg\]: the others
    /// are summed as deviations from it (small numbers, little rounding).
    first: [f32; 5],
    /// Sums of the deviations from `first` \[deg\] (f32, compensated:
    /// no f64 soft-float on the board, issue 50 item 7).
    sums: [f32; 5],
    /// The compensation terms of `sums` (Kahan-Babuška/Neumaier).
    comp: [f32; 5],
}

/// A finished capture: the mean angles and how many samples made them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Captured {
    /// Mean θ1, θ2, θ, pitch, yaw \[deg\] (NaN when no sample was valid).
    pub angles_deg: [f32; 5],
    /// Valid samples averaged.
    pub used: u16,
}

impl Capture {
    /// A capture of `n` valid samples (at least 1).
    pub fn new(n: u16) -> Self {
        Self {
            want: n.max(1),
            ..Self::default()
        }
    }

    /// Adds one sample; returns the result once the capture is complete.
    pub fn add(&mut self, o: &Output) -> Option<Captured> {
        self.seen += 1;
        if o.valid() {
            let a = [
                o.theta1_deg,
                o.theta2_deg,
                o.theta_deg,
                o.pitch_deg,
                o.yaw_deg,
            ];
            if self.used == 0 {
                self.first = a;
            }
            for (k, &v) in a.iter().enumerate() {
                let d = v - self.first[k];
                let t = self.sums[k] + d;
                // Neumaier: the low-order bits the addition lost
                self.comp[k] += if self.sums[k].abs() >= d.abs() {
                    (self.sums[k] - t) + d
                } else {
                    (d - t) + self.sums[k]
                };
                self.sums[k] = t;
            }
            self.used += 1;
        }
        let done = self.used >= self.want || self.seen >= PATIENCE * u32::from(self.want);
        done.then(|| self.result())
    }

    fn result(&self) -> Captured {
        let n = f32::from(self.used);
        Captured {
            angles_deg: core::array::from_fn(|k| self.first[k] + (self.sums[k] + self.comp[k]) / n),
            used: self.used,
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::status::{NO_PLANE, SENSOR_VALID};

    fn out(theta1: f32, valid: bool) -> Output {
        Output {
            status: if valid {
                SENSOR_VALID * 0x1111
            } else {
                NO_PLANE
            },
            theta1_deg: theta1,
            theta2_deg: -theta1,
            theta_deg: 2.0,
            pitch_deg: 0.5,
            yaw_deg: -0.5,
            ..Output::default()
        }
    }

    #[test]
    fn averages_the_valid_samples() {
        let mut c = Capture::new(4);
        assert_eq!(c.add(&out(1.0, true)), None);
        assert_eq!(c.add(&out(9.0, false)), None, "skipped");
        assert_eq!(c.add(&out(2.0, true)), None);
        assert_eq!(c.add(&out(3.0, true)), None);
        let r = c.add(&out(6.0, true)).unwrap();
        assert_eq!(r.used, 4);
        assert_eq!(r.angles_deg, [3.0, -3.0, 2.0, 0.5, -0.5]);
    }

    #[test]
    fn the_f32_mean_of_a_thousand_samples_matches_f64() {
        let mut c = Capture::new(1000);
        let mut exact = 0.0f64;
        let mut r = None;
        for k in 0..1000u32 {
            let v = 12.345_678 + 1e-3 * ((k * 7919 % 1000) as f32 - 500.0) / 500.0;
            exact += f64::from(v);
            r = c.add(&out(v, true));
        }
        let r = r.unwrap();
        let want = (exact / 1000.0) as f32;
        assert!(
            (r.angles_deg[0] - want).abs() <= 2.0 * f32::EPSILON * want.abs(),
            "{} vs {want}",
            r.angles_deg[0]
        );
        assert_eq!(r.angles_deg[2], 2.0);
    }

    #[test]
    fn gives_up_after_four_times_n_samples() {
        let mut c = Capture::new(2);
        assert_eq!(c.add(&out(1.0, true)), None);
        for _ in 0..6 {
            assert_eq!(c.add(&out(0.0, false)), None);
        }
        let r = c.add(&out(0.0, false)).unwrap();
        assert_eq!((r.used, r.angles_deg[0]), (1, 1.0));
        let mut none = Capture::new(1);
        for _ in 0..3 {
            assert_eq!(none.add(&out(0.0, false)), None);
        }
        let r = none.add(&out(0.0, false)).unwrap();
        assert_eq!(r.used, 0);
        assert!(r.angles_deg[0].is_nan());
    }
}

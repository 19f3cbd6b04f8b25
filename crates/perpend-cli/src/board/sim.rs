//! The simulated sensor head of the virtual board: the true head looks at
//! a fixed plane; each sample turns the true distances into the ADC
//! results the board's channels would show, with seeded Gaussian noise and
//! injected faults.
//!
//! Per sensor `i`: `d_true` from the beam/plane model (Chen eq. 1-3,
//! [`perpend_core::model::distance`]); the reading the sensor outputs is
//! `d = d_true + δ(d)` for the true head's extension corrections
//! ([`perpend_core::ext`], solved by two fixed-point steps, so that the
//! board's correction `d − δ(d)` gives `d_true` back), plus noise; then
//! mm → signal → counts through the channel's transfer function
//! ([`perpend_board::acq::signal_for_mm`], [`perpend_board::acq::counts_for_signal`]).
//!
//! A beam that misses the plane outputs 3.7 mA / 0.74 % below the span
//! (NE43 "out of range"). Faults replace the signal: open loop 0 mA,
//! overcurrent 24 mA, saturated 20.8 mA (out of range high), stuck (the
//! counts of the first faulted sample forever), noisy (extra 0.3 mm 1σ).
//!
//! Limits: no temperature or time effects (the board is fed neither).

use std::fmt;
use std::str::FromStr;

use anyhow::{bail, Result};
use perpend_board::acq::{counts_for_signal, signal_for_mm};
use perpend_core::ext::Context;
use perpend_core::geometry::Plane;
use perpend_core::head::Head4;
use perpend_core::model::distance;
use perpend_core::params::{Acquisition, Transfer};
use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};

/// Extra noise of a `noisy` sensor [mm, 1σ].
pub const NOISY_MM: f64 = 0.3;

/// A fault injected into one sensor.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaultKind {
    /// Current loop open: 0 mA (0 V for voltage sensors).
    Open,
    /// Loop current above the NE43 band: 24 mA (or 12 V).
    Overcurrent,
    /// Saturated output in the out-of-range band above the span.
    Saturated,
    /// Output frozen at its value when the fault starts.
    Stuck,
    /// Much noisier than the others ([`NOISY_MM`]).
    Noisy,
}

impl FromStr for FaultKind {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "open" => FaultKind::Open,
            "overcurrent" => FaultKind::Overcurrent,
            "saturated" => FaultKind::Saturated,
            "stuck" => FaultKind::Stuck,
            "noisy" => FaultKind::Noisy,
            _ => {
                bail!("unknown fault '{s}': expected open, overcurrent, saturated, stuck or noisy")
            }
        })
    }
}

impl fmt::Display for FaultKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            FaultKind::Open => "open",
            FaultKind::Overcurrent => "overcurrent",
            FaultKind::Saturated => "saturated",
            FaultKind::Stuck => "stuck",
            FaultKind::Noisy => "noisy",
        })
    }
}

/// `SENSOR:KIND` with SENSOR 1-based (the `--fault` argument).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Fault {
    /// Sensor, 0-based.
    pub sensor: usize,
    /// What is wrong with it.
    pub kind: FaultKind,
}

impl FromStr for Fault {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        let Some((n, k)) = s.split_once(':') else {
            bail!("--fault '{s}': expected SENSOR:KIND, e.g. 2:open");
        };
        let n: usize = n
            .trim()
            .parse()
            .map_err(|_| anyhow::anyhow!("--fault '{s}': sensor must be 1..4"))?;
        if !(1..=4).contains(&n) {
            bail!("--fault '{s}': sensor must be 1..4");
        }
        Ok(Fault {
            sensor: n - 1,
            kind: k.trim().parse()?,
        })
    }
}

/// The simulated head.
#[derive(Debug, Clone)]
pub struct SimHead {
    truth: Head4<f64>,
    plane: Plane<f64>,
    noise: Normal<f64>,
    noisy: Normal<f64>,
    rng: StdRng,
    faults: [Option<FaultKind>; 4],
    frozen: [Option<u16>; 4],
    /// Die temperature the board measures \[°C\] (`None`: no sensor).
    temp_c: Option<f64>,
}

impl SimHead {
    /// A head `truth` looking at `plane`, with reading noise `noise_mm`
    /// (1σ) drawn from a generator seeded with `seed`.
    ///
    /// # Errors
    /// A negative or non-finite noise.
    pub fn new(truth: Head4<f64>, plane: Plane<f64>, noise_mm: f64, seed: u64) -> Result<Self> {
        if !(noise_mm.is_finite() && noise_mm >= 0.0) {
            bail!("--noise-mm {noise_mm}: must be finite and >= 0");
        }
        let noise = Normal::new(0.0, noise_mm)
            .map_err(|_| anyhow::anyhow!("--noise-mm {noise_mm}: must be finite and >= 0"))?;
        let noisy = Normal::new(0.0, (noise_mm * noise_mm + NOISY_MM * NOISY_MM).sqrt())
            .map_err(|_| anyhow::anyhow!("--noise-mm {noise_mm}: must be finite and >= 0"))?;
        Ok(Self {
            truth,
            plane,
            noise,
            noisy,
            rng: StdRng::seed_from_u64(seed),
            faults: [None; 4],
            frozen: [None; 4],
            temp_c: None,
        })
    }

    /// Sets the die temperature the board measures (`perpend board
    /// --temp-c`): every sample carries it, the board publishes it in
    /// 0x200A and applies the thermal correction with it.
    pub fn set_temp_c(&mut self, t: Option<f64>) {
        self.temp_c = t.filter(|t| t.is_finite());
    }

    /// The die temperature of the next sample, if simulated.
    pub fn temp_c(&self) -> Option<f64> {
        self.temp_c
    }

    /// Injects (or with `None` removes) a fault on sensor `i` (0-based).
    pub fn set_fault(&mut self, i: usize, kind: Option<FaultKind>) {
        if let Some(f) = self.faults.get_mut(i) {
            *f = kind;
            self.frozen[i] = None;
        }
    }

    /// The plane the head looks at.
    pub fn plane(&self) -> &Plane<f64> {
        &self.plane
    }

    /// Moves the plane the head looks at (the simulated robot of
    /// `perpend board --world`); stuck sensors stay frozen.
    pub fn set_plane(&mut self, plane: Plane<f64>) {
        self.plane = plane;
    }

    /// The true distances (no extension effects, no noise); `None` where
    /// the beam misses the plane.
    pub fn true_distances(&self) -> [Option<f64>; 4] {
        core::array::from_fn(|i| distance(&self.truth.sensors[i], &self.plane, i).ok())
    }

    /// The distance sensor `i` outputs for true distance `d_true` given the
    /// true distance of the previously converted channel: the inverse of
    /// the extension correction (module docs).
    fn output_mm(&self, i: usize, d_true: f64, d_prev: Option<f64>) -> f64 {
        let s = &self.truth.sensors[i];
        let cos_g = self.plane.n.dot(&s.dir).abs();
        let ctx = Context::default();
        d_true + s.ext.excess(d_true, d_prev, cos_g, &ctx)
    }

    /// One ADC scan: the counts of the four channels for the board's
    /// transfer functions and acquisition settings.
    pub fn sample(&mut self, transfer: &[Transfer; 4], acq: &Acquisition) -> [u16; 4] {
        let d = self.true_distances();
        let mut counts = [0u16; 4];
        for i in 0..4 {
            let t = &transfer[i];
            let span = t.sig_hi - t.sig_lo;
            let out_of_range = t.sig_lo - 0.01875 * span;
            let mm = d[i].map(|dt| self.output_mm(i, dt, d[(i + 3) % 4]));
            let signal = match self.faults[i] {
                Some(FaultKind::Open) => 0.0,
                Some(FaultKind::Overcurrent) => t.sig_lo + 1.25 * span,
                Some(FaultKind::Saturated) => t.sig_lo + 1.05 * span,
                Some(FaultKind::Noisy) => match mm {
                    Some(m) => signal_for_mm((m + self.noisy.sample(&mut self.rng)) as f32, t),
                    None => out_of_range,
                },
                Some(FaultKind::Stuck) | None => match mm {
                    Some(m) => signal_for_mm((m + self.noise.sample(&mut self.rng)) as f32, t),
                    None => out_of_range,
                },
            };
            let c = counts_for_signal(signal, t, acq);
            counts[i] = if self.faults[i] == Some(FaultKind::Stuck) {
                *self.frozen[i].get_or_insert(c)
            } else {
                c
            };
        }
        counts
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use perpend_board::acq::{convert, Class};
    use perpend_core::params::Params;

    fn head() -> (SimHead, Params) {
        let p = Params::factory();
        let plane = Plane::from_abcd(0.035, -0.052, 1.0, -40.0).unwrap();
        (SimHead::new(p.head.cast(), plane, 0.0, 1).unwrap(), p)
    }

    #[test]
    fn counts_convert_back_to_the_true_distances() {
        let (mut s, p) = head();
        let c = s.sample(&p.transfer, &p.acq);
        let d = s.true_distances();
        for i in 0..4 {
            let conv = convert(c[i], &p.transfer[i], &p.acq);
            assert_eq!(conv.class, Class::Valid);
            // one count of a 16-bit result over 60 mm is ~1.3 µm
            assert!((conv.mm as f64 - d[i].unwrap()).abs() < 2e-3, "{i}");
        }
    }

    #[test]
    fn faults_produce_their_classes() {
        let (mut s, p) = head();
        let cases = [
            (FaultKind::Open, Class::OpenLoop),
            (FaultKind::Overcurrent, Class::Overcurrent),
            (FaultKind::Saturated, Class::OutOfRange),
        ];
        for (k, want) in cases {
            s.set_fault(1, Some(k));
            let c = s.sample(&p.transfer, &p.acq);
            assert_eq!(convert(c[1], &p.transfer[1], &p.acq).class, want, "{k}");
        }
        s.set_fault(1, Some(FaultKind::Stuck));
        let first = s.sample(&p.transfer, &p.acq)[1];
        let mut noisy = SimHead::new(Params::factory().head.cast(), *s.plane(), 0.01, 3).unwrap();
        noisy.set_fault(1, Some(FaultKind::Stuck));
        let a = noisy.sample(&p.transfer, &p.acq);
        for _ in 0..20 {
            let b = noisy.sample(&p.transfer, &p.acq);
            assert_eq!(a[1], b[1]);
        }
        assert!(first > 0);
    }

    #[test]
    fn parses_fault_arguments() {
        assert_eq!(
            "2:open".parse::<Fault>().unwrap(),
            Fault {
                sensor: 1,
                kind: FaultKind::Open
            }
        );
        assert!("5:open".parse::<Fault>().is_err());
        assert!("1:melted".parse::<Fault>().is_err());
        assert!("open".parse::<Fault>().is_err());
        assert!(SimHead::new(Params::factory().head.cast(), *head().0.plane(), -1.0, 0).is_err());
    }
}

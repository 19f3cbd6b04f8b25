//! The temperature the thermal extension sees: the head thermometer (the
//! MCU's die sensor, object 0x200A) passed through the first-order lag of
//! the head's thermal time constant τ (object 0x2105,
//! `Params::thermal_tau_s`): the sensor bodies follow the thermometer as
//! `τ·dy/dt = u − y` (`perpend_core::lag`, Newton's law of cooling).
//!
//! ## Stepping at the temperature's own pace
//!
//! The state `y` is committed with the exact step
//! `perpend_core::lag::step` (first-order hold: the input linear between
//! the last committed input and the newest) only once at least
//! `min(1 s, τ/100)` has passed since the last commit, and never more than
//! once per sample (so at least one sample interval apart). Stepped every
//! millisecond in `f32`, each step would change `y` by a few ulps and the
//! rounding would accumulate (`perpend_core::lag`, "Precision"); once a
//! second the change is a thousand ulps. Between commits every sample
//! gets the lag from the committed state to its own time and temperature
//! with the same first-order hold (`lag::step_short`: the exponential's
//! series, a division and a few multiply-adds, exact to `f32` rounding for
//! `dt ≤ τ/16`); this value is not committed, so nothing accumulates and
//! the output agrees with `lag::filter` of the same samples as long as the
//! temperature is smooth over a commit interval (a warm-up: within 2e-3
//! °C, tests). A jump between commits is seen as a ramp from the last
//! commit: the output is then up to `jump·interval/(2τ)` off the filter of
//! every sample (bound 0.05 °C for 10 °C at τ = 30 s, 0.017 °C
//! measured), and close to it again from the next commit on (4e-5 °C in
//! that case).
//!
//! Time is the `now_us` of [`crate::app::App::on_sample`] (µs since
//! power-on, `u64`: no wrap).
//!
//! ## Rules
//!
//! * `τ = 0` (or not positive): no lag, the thermometer's reading is
//!   passed as it is (the behaviour without 0x2105), and the state is
//!   dropped: a later `τ > 0` starts at rest.
//! * The first valid temperature starts the lag **at rest** (`y = u`): the
//!   board cannot know how far the head was from equilibrium at power-on.
//! * A missing or non-finite temperature holds the state (no step). The
//!   corrections then get the last lagged value if a temperature was ever
//!   seen (the sensor bodies do not lose their temperature because one
//!   conversion failed), else none (the thermal term contributes nothing,
//!   as without a thermometer). The next valid temperature is stepped to
//!   from the committed state, the input taken as linear over the gap.
//! * Time going backwards (before the last valid temperature) restarts at
//!   rest at the new temperature. A gap of any length is one exact step
//!   (the input linear over it), as `lag::filter` on the host steps it:
//!   no restart after some number of τ, which would jump by up to a tenth
//!   of the temperature change across the gap (at 10 τ the ramp term
//!   `(u1 − u0)·φ` is still `(u1 − u0)/10`; only the initial state is
//!   forgotten, to `e^{-10}`).
//! * A τ changed over CAN applies from the next sample on: the committed
//!   state is kept (no reset) and the next step uses the new τ.
//!
//! Limits: one τ for the head; the thermometer is taken as the head
//! temperature (the board sits in the head).

use perpend_core::lag;

/// Longest time between two committed steps \[s\].
pub const STEP_MAX_S: f32 = 1.0;
/// Committed steps are at least τ divided by this apart (when shorter than
/// [`STEP_MAX_S`]).
pub const STEPS_PER_TAU: f32 = 100.0;

/// The lag's state (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ThermalLag {
    /// Lagged temperature at the last commit \[°C\].
    y: f32,
    /// Thermometer reading at the last commit \[°C\].
    u0: f32,
    /// Time of the last commit \[µs\].
    t0_us: u64,
    /// Time of the last valid temperature \[µs\].
    last_us: u64,
    /// The value handed out for the last valid temperature \[°C\].
    out: f32,
    /// A valid temperature was seen since the last (re)start.
    started: bool,
}

impl ThermalLag {
    /// A lag that has seen no temperature yet.
    pub const fn new() -> Self {
        Self {
            y: 0.0,
            u0: 0.0,
            t0_us: 0,
            last_us: 0,
            out: 0.0,
            started: false,
        }
    }

    /// Whether a temperature was seen since the last (re)start.
    pub fn started(&self) -> bool {
        self.started
    }

    /// The temperature the corrections get for a sample taken at `now_us`
    /// whose thermometer read `temp_c`, with time constant `tau_s` \[s\]
    /// (module docs for every rule).
    pub fn update(&mut self, temp_c: Option<f32>, now_us: u64, tau_s: f32) -> Option<f32> {
        if !(tau_s > 0.0) {
            self.started = false;
            return temp_c;
        }
        let Some(u) = temp_c.filter(|t| t.is_finite()) else {
            return self.started.then_some(self.out);
        };
        if !self.started || now_us < self.last_us {
            return Some(self.restart(u, now_us));
        }
        self.last_us = now_us;
        let dt = secs(now_us - self.t0_us);
        if dt >= STEP_MAX_S.min(tau_s / STEPS_PER_TAU) {
            self.y = lag::step(self.y, self.u0, u, dt, tau_s);
            self.u0 = u;
            self.t0_us = now_us;
            self.out = self.y;
        } else {
            self.out = lag::step_short(self.y, self.u0, u, dt, tau_s);
        }
        Some(self.out)
    }

    /// Starts at rest at `u` at `now_us`; returns `u`.
    fn restart(&mut self, u: f32, now_us: u64) -> f32 {
        *self = Self {
            y: u,
            u0: u,
            t0_us: now_us,
            last_us: now_us,
            out: u,
            started: true,
        };
        u
    }
}

/// Microseconds to seconds in `f32` through the FPU's `u32` conversion
/// (no software `u64` one): below 2^32 µs (71 min) directly, beyond as
/// whole 2^20 µs units plus the rest (within one `f32` rounding; beyond
/// 2^52 µs, 142 years, saturated).
fn secs(us: u64) -> f32 {
    match u32::try_from(us) {
        Ok(v) => v as f32 * 1e-6,
        Err(_) => {
            let hi = u32::try_from(us >> 20).unwrap_or(u32::MAX) as f32 * 1.048_576;
            hi + (us & 0xF_FFFF) as u32 as f32 * 1e-6
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// The warm-up of a head: 20 °C + 8 °C·(1 − e^{−t/900 s}).
    fn warm_up(t: f64) -> f64 {
        20.0 + 8.0 * (1.0 - (-t / 900.0).exp())
    }

    /// Feeds `warm_up` at `hz` for `secs` through a [`ThermalLag`] of
    /// time constant `tau` and through `lag::filter` in f64 (same sample
    /// times, inputs rounded to f32 as the board reads them); returns the
    /// largest difference at any sample and the number of commits.
    fn against_filter(hz: u64, secs: u64, tau: f64) -> (f64, u32) {
        let n = (hz * secs) as usize + 1;
        let period_us = 1_000_000 / hz;
        let t_us: Vec<u64> = (0..n as u64).map(|k| 5_000 + k * period_us).collect();
        let t: Vec<f64> = t_us.iter().map(|&x| x as f64 * 1e-6).collect();
        let u: Vec<f64> = t.iter().map(|&x| warm_up(x) as f32 as f64).collect();
        let mut want = vec![0.0; n];
        lag::filter(&t, &u, tau, &mut want);
        let mut l = ThermalLag::new();
        let (mut worst, mut commits, mut t0) = (0.0f64, 0u32, t_us[0]);
        for k in 0..n {
            let got = l.update(Some(u[k] as f32), t_us[k], tau as f32).unwrap();
            worst = worst.max((got as f64 - want[k]).abs());
            if l.t0_us != t0 {
                commits += 1;
                t0 = l.t0_us;
            }
        }
        (worst, commits)
    }

    /// (a) 10 Hz over an hour: within 2e-3 °C of the f64 filter at every
    /// sample, for a long and a short τ; committed once a second (τ = 600)
    /// or every τ/100 (τ = 40 s: 0.4 s, i.e. every 4th sample).
    #[test]
    fn warm_up_at_10_hz_follows_the_filter() {
        let (worst, commits) = against_filter(10, 3600, 600.0);
        assert!(worst < 2e-3, "{worst}");
        assert_eq!(commits, 3600);
        let (worst, commits) = against_filter(10, 3600, 40.0);
        assert!(worst < 2e-3, "{worst}");
        assert_eq!(commits, 9000);
        // the lag is there: the sensors trail the thermometer early on
        let mut l = ThermalLag::new();
        l.update(Some(20.0), 0, 600.0);
        let y = l.update(Some(warm_up(600.0) as f32), 600_000_000, 600.0);
        assert!(y.unwrap() < warm_up(600.0) as f32 - 1.0);
    }

    /// (b) 1 kHz over 10 min: committing once a second keeps f32 from
    /// losing the millisecond steps (each would be a few ulps).
    #[test]
    fn warm_up_at_1_khz_loses_no_precision() {
        let (worst, commits) = against_filter(1000, 600, 900.0);
        assert!(worst < 2e-3, "{worst}");
        assert_eq!(commits, 600);
    }

    /// A long τ over an 8-hour warm-up: within 1e-3 °C of the f64 filter
    /// at τ = 1 day (1 Hz) and 2e-4 °C at τ = 20 000 s (10 Hz); with the
    /// decay `a` rounded near 1 in `lag::step` 2.0e-3 and 5.8e-4 °C.
    #[test]
    fn long_tau_keeps_its_precision() {
        let (worst, commits) = against_filter(1, 8 * 3600, 86_400.0);
        assert!(worst < 1e-3, "{worst}");
        assert_eq!(commits, 8 * 3600);
        let (worst, _) = against_filter(10, 8 * 3600, 20_000.0);
        assert!(worst < 2e-4, "{worst}");
    }

    /// (d) A missing or non-finite temperature holds the state: nothing
    /// before the first valid one; after it the last lagged value, and the
    /// next valid temperature is stepped to across the gap.
    #[test]
    fn missing_temperature_holds() {
        let tau = 100.0;
        let mut l = ThermalLag::new();
        assert_eq!(l.update(None, 0, tau), None);
        assert_eq!(l.update(Some(f32::NAN), 1_000, tau), None);
        assert!(!l.started());
        assert_eq!(l.update(Some(20.0), 2_000, tau), Some(20.0));
        let y1 = l.update(Some(30.0), 10_002_000, tau).unwrap();
        let want = lag::step(20.0f64, 20.0, 30.0, 10.0, tau as f64);
        assert!((y1 as f64 - want).abs() < 1e-5, "{y1} {want}");
        let held = l;
        assert_eq!(l.update(None, 11_000_000, tau), Some(y1));
        assert_eq!(l.update(Some(f32::INFINITY), 12_000_000, tau), Some(y1));
        assert_eq!(l, held, "no step");
        // back after 20 s without a temperature: one step over the gap
        let y2 = l.update(Some(30.0), 30_002_000, tau).unwrap();
        let want2 = lag::step(want, 30.0, 30.0, 20.0, tau as f64);
        assert!((y2 as f64 - want2).abs() < 1e-5, "{y2} {want2}");
        // τ = 0: the reading as it is, the state dropped
        assert_eq!(l.update(Some(25.0), 30_003_000, 0.0), Some(25.0));
        assert_eq!(l.update(None, 30_004_000, 0.0), None);
        assert!(!l.started());
        assert_eq!(l.update(Some(26.0), 30_005_000, tau), Some(26.0));
    }

    /// (d) Time going backwards restarts at rest; a gap of any length is
    /// one exact step from the committed state, as `lag::filter` steps it
    /// (a gap beyond 10 τ used to restart at rest: 0.9 °C off the filter
    /// for 20 → 30 °C across 11 τ).
    #[test]
    fn backwards_time_restarts_and_long_gaps_step() {
        let tau = 50.0;
        let mut l = ThermalLag::new();
        l.update(Some(20.0), 1_000_000_000, tau);
        let y = l.update(Some(30.0), 1_010_000_000, tau).unwrap();
        assert!(y > 20.0 && y < 25.0);
        assert_eq!(l.update(Some(31.0), 1_009_000_000, tau), Some(31.0));
        // within 10 τ (499 s): stepped from the restart, not at rest
        let y = l.update(Some(35.0), 1_508_000_000, tau).unwrap();
        let want = lag::step(31.0f64, 31.0, 35.0, 499.0, tau as f64);
        assert!((y as f64 - want).abs() < 1e-4 && y < 34.7, "{y} {want}");
        // beyond 10 τ (550 s): the same exact step, as the host's filter
        let y2 = l.update(Some(22.0), 2_058_000_000, tau).unwrap();
        let want2 = lag::step(want, 35.0, 22.0, 550.0, tau as f64);
        assert!((y2 as f64 - want2).abs() < 1e-4, "{y2} {want2}");
        assert!(y2 > 23.0, "not restarted at rest: {y2}");
        let mut fresh = ThermalLag::new();
        fresh.update(Some(20.0), 0, tau);
        let y = fresh.update(Some(30.0), 550_000_000, tau).unwrap();
        let mut want = [0.0; 2];
        lag::filter(&[0.0, 550.0], &[20.0, 30.0], tau as f64, &mut want);
        assert!((y as f64 - want[1]).abs() < 1e-4, "{y} {want:?}");
        // a gap beyond 2^32 µs goes through the u64 conversion
        assert_eq!(secs(5_000_000_000), 5_000.0);
        for us in [
            4_294_967_296u64,
            86_400_000_000 * 10 + 123_457,
            u64::MAX >> 12,
        ] {
            let want = us as f64 * 1e-6;
            assert!((secs(us) as f64 - want).abs() <= want * 2e-7, "{us}");
        }
        let y3 = l.update(Some(23.0), 7_058_000_000, 86_400.0).unwrap();
        let want3 = lag::step(want2, 22.0, 23.0, 5_000.0, 86_400.0);
        assert!((y3 as f64 - want3).abs() < 1e-4, "{y3} {want3}");
    }

    /// A τ changed between samples applies at once from the committed
    /// state, without a restart.
    #[test]
    fn changed_tau_applies_without_reset() {
        let mut l = ThermalLag::new();
        l.update(Some(20.0), 0, 600.0);
        l.update(Some(20.0), 2_000_000, 600.0);
        let y = l.update(Some(30.0), 3_000_000, 60.0).unwrap();
        let want = lag::step(20.0f64, 20.0, 30.0, 1.0, 60.0);
        assert!((y as f64 - want).abs() < 1e-5);
        assert!(l.started());
    }
}

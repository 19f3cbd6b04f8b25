//! The temperature the thermal extension sees: the head thermometer (the
//! MCU's die sensor, object 0x200A) passed through the first-order lag of
//! the head's thermal time constant τ (object 0x2105,
//! `Params::thermal_tau_s`): the sensor bodies follow the thermometer as
//! `τ·dy/dt = u − y` (`perpend_core::lag`, Newton's law of cooling).
//!
//! ## Stepping at the temperature's own pace
//!
//! The state `y` is committed with the exact step of `perpend_core::lag`
//! (first-order hold: the input linear between the last committed input
//! and the newest) on a fixed grid of period `P = min(1 s, τ/100)` (whole
//! µs): stepped every millisecond in `f32`, each step would change `y` by
//! a few ulps and the rounding would accumulate (`perpend_core::lag`,
//! "Precision"); once a second the change is a thousand ulps. The step's
//! coefficients `1 − a`, `φ` for `P` are computed once per τ
//! (`lag::coefficients`, with `expm1f`), so a commit is a few
//! multiply-adds, bit for bit `lag::step` over `P`:
//!
//! * a sample at or after the next grid time `t0 + P` (and before
//!   `t0 + 2P`) commits the step to the grid time, the input there taken
//!   on the line from the committed input to this sample's (a sample on
//!   the grid: this sample's input itself);
//! * a sample `2P` or more after the last commit (a gap, samples sparser
//!   than `P`, a changed τ) commits the exact step `lag::step` over the
//!   whole interval (`expm1f`) and restarts the grid at this sample.
//!
//! Every sample gets the lag from the committed state to its own time and
//! temperature (after the commit, if any) by the step's expansion to
//! second order in `x = dt/τ ≤ 1/100`: `1 − a ≈ x − x²/2`,
//! `1 − φ ≈ x/2 − x²/6`, with `1/τ` per µs cached (no exponential, no
//! division). It is not committed, so nothing accumulates; its truncation
//! is at most `x³/6·|u0 − y| + x³/24·|u − u0|` (≤ 1.7e-7 of the lag
//! difference). For a warm-up (20 + 8(1 − e^{−t/900 s}) °C, τ = 40 s..1
//! day, 1 Hz..1 kHz, on and off the grid) the output stays within 1e-4
//! °C of `lag::filter` in f64 at every sample (3.3e-5 measured, tests;
//! long τ: the f32 commits' own 5.7e-4 at τ = 1 day). Cheaper
//! alternatives measured against the same tests: the last committed value
//! alone is 3.6e-3 °C off at τ = 600 s (6.1e-3 at τ = 100 s), above the
//! 2e-3 °C allowed; the first order alone (4 instructions fewer) 1.6e-4
//! °C after a 10 °C jump, against 1e-5 for the exact step. A jump between
//! commits is seen as a ramp from the last commit: the output is then up
//! to `jump·P/(2τ)` off the filter of every sample (bound 0.05 °C for 10
//! °C at τ = 30 s), and close to it again from the next commit on.
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
//!   rest at the new temperature. A gap of `2P` or more is one exact step
//!   (the input linear over it), as `lag::filter` on the host steps it (a
//!   shorter one is a commit on the grid and the expansion):
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

/// Longest period `P` of the commit grid \[s\].
pub const STEP_MAX_S: f32 = 1.0;
/// The grid's period is τ divided by this (when shorter than
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
    /// The step of one grid period, for the τ it was made for.
    grid: Grid,
}

/// What a commit on the grid and the expansion between commits need, for
/// one τ (the module docs): computed when τ changes.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct Grid {
    /// τ these are for \[s\] (0: none yet).
    tau_s: f32,
    /// The period `P` \[µs\], at least 1.
    period_us: u32,
    /// `1/τ` per µs: `x = dt·per_us`.
    per_us: f32,
    /// `1 − a` and `φ` of a step of `P` (`lag::coefficients`).
    one_minus_a: f32,
    phi: f32,
}

impl Grid {
    /// The grid of `tau_s` (positive). An infinite τ is no lag, as in
    /// `lag::step`: a grid of 1 µs whose step lands on the input.
    fn new(tau_s: f32) -> Self {
        if !tau_s.is_finite() {
            return Self {
                tau_s,
                period_us: 1,
                per_us: 0.0,
                one_minus_a: 1.0,
                phi: 0.0,
            };
        }
        let p_s = STEP_MAX_S.min(tau_s / STEPS_PER_TAU);
        // whole µs, at least one; p_s ≤ 1 s, so the cast cannot saturate
        let period_us = ((p_s * 1e6 + 0.5) as u32).max(1);
        let (one_minus_a, phi) =
            lag::coefficients(secs(u64::from(period_us)), tau_s).unwrap_or((0.0, 1.0));
        Self {
            tau_s,
            period_us,
            per_us: 1e-6 / tau_s,
            one_minus_a,
            phi,
        }
    }
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
            grid: Grid {
                tau_s: 0.0,
                period_us: 1,
                per_us: 0.0,
                one_minus_a: 0.0,
                phi: 1.0,
            },
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
        if tau_s != self.grid.tau_s {
            self.grid = Grid::new(tau_s);
        }
        self.last_us = now_us;
        let period = u64::from(self.grid.period_us);
        let mut dt = now_us - self.t0_us;
        if dt >= period {
            dt = self.commit(u, dt, now_us, tau_s);
        }
        // the second-order expansion from the commit (dt < P < 2^32 µs)
        let x = dt as u32 as f32 * self.grid.per_us;
        let (a, d) = (self.u0 - self.y, u - self.u0);
        let first = a + 0.5 * d;
        let second = 0.5 * a + d * (1.0 / 6.0);
        self.out = self.y + x * (first - x * second);
        Some(self.out)
    }

    /// Commits the step to the next grid time, or over all of `dt` (µs
    /// since the last commit, at least `P`) when that is `2P` or more
    /// (module docs); returns the time left from the new commit to
    /// `now_us`.
    fn commit(&mut self, u: f32, dt: u64, now_us: u64, tau_s: f32) -> u64 {
        let g = self.grid;
        let period = u64::from(g.period_us);
        if dt - period >= period {
            self.y = lag::step(self.y, self.u0, u, secs(dt), tau_s);
            self.u0 = u;
            self.t0_us = now_us;
            return 0;
        }
        let ug = if dt == period {
            u
        } else {
            // dt < 2P ≤ 2 s: exact in f32
            self.u0 + (u - self.u0) * (g.period_us as f32 / dt as u32 as f32)
        };
        self.y = lag::increment(self.y, self.u0, ug, g.one_minus_a, g.phi);
        self.u0 = ug;
        self.t0_us += period;
        dt - period
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
            grid: self.grid,
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
        let n = hz * secs + 1;
        let period_us = 1_000_000 / hz;
        let t_us: Vec<u64> = (0..n).map(|k| 5_000 + k * period_us).collect();
        against_filter_at(&t_us, tau).0
    }

    /// As [`against_filter`] at the sample times `t_us`; also returns the
    /// largest difference of the last committed value alone (what the
    /// board would hand out without the expansion between commits).
    fn against_filter_at(t_us: &[u64], tau: f64) -> ((f64, u32), f64) {
        let n = t_us.len();
        let t: Vec<f64> = t_us.iter().map(|&x| x as f64 * 1e-6).collect();
        let u: Vec<f64> = t.iter().map(|&x| warm_up(x) as f32 as f64).collect();
        let mut want = vec![0.0; n];
        lag::filter(&t, &u, tau, &mut want);
        let mut l = ThermalLag::new();
        let (mut worst, mut commits, mut t0) = (0.0f64, 0u32, t_us[0]);
        let mut held = 0.0f64;
        for k in 0..n {
            let got = l.update(Some(u[k] as f32), t_us[k], tau as f32).unwrap();
            worst = worst.max((got as f64 - want[k]).abs());
            held = held.max((l.y as f64 - want[k]).abs());
            if l.t0_us != t0 {
                commits += 1;
                t0 = l.t0_us;
            }
        }
        ((worst, commits), held)
    }

    /// (a) 10 Hz over an hour: within 1e-4 °C of the f64 filter at every
    /// sample (3.3e-5 and 1.6e-5 measured), for a long and a short τ;
    /// committed once a second (τ = 600) or every τ/100 (τ = 40 s: 0.4 s,
    /// i.e. every 4th sample). The last committed value alone, handed out
    /// between commits, would be 3.6e-3 / 2.3e-3 °C off (6.1e-3 at τ =
    /// 100 s): above the 2e-3 °C the board allows, hence the expansion.
    #[test]
    fn warm_up_at_10_hz_follows_the_filter() {
        for (tau, want_commits, held_min) in [(600.0, 3600, 3e-3), (40.0, 9000, 2e-3)] {
            let t_us: Vec<u64> = (0..=36_000).map(|k| 5_000 + k * 100_000).collect();
            let ((worst, commits), held) = against_filter_at(&t_us, tau);
            assert!(worst < 1e-4, "τ = {tau}: {worst}");
            assert_eq!(commits, want_commits);
            assert!(held > held_min, "τ = {tau}: {held}");
        }
        // the lag is there: the sensors trail the thermometer early on
        let mut l = ThermalLag::new();
        l.update(Some(20.0), 0, 600.0);
        let y = l.update(Some(warm_up(600.0) as f32), 600_000_000, 600.0);
        assert!(y.unwrap() < warm_up(600.0) as f32 - 1.0);
    }

    /// (b) 1 kHz over 10 min: committing once a second keeps f32 from
    /// losing the millisecond steps (each would be a few ulps); the 999
    /// samples between commits within 1e-4 °C (1.3e-5 measured).
    #[test]
    fn warm_up_at_1_khz_loses_no_precision() {
        let (worst, commits) = against_filter(1000, 600, 900.0);
        assert!(worst < 1e-4, "{worst}");
        assert_eq!(commits, 600);
    }

    /// Sample times off the commit grid: 1 kHz with up to 0.3 ms of
    /// jitter (commits at the grid time, the input interpolated to it),
    /// 3 Hz at τ = 40 s (P = 0.4 s: five samples in six commit one period
    /// on the grid and expand over the rest, 1500 commits), 1 Hz at τ = 40 s (every sample 2P or more
    /// after the last commit: the exact step over the whole interval).
    /// All within 1e-4 °C of the f64 filter over 10 min.
    #[test]
    fn off_grid_samples_follow_the_filter() {
        let jitter: Vec<u64> = (0..=600_000u64)
            .map(|k| 5_000 + k * 1_000 + (k * 7_919) % 300)
            .collect();
        for tau in [600.0, 40.0] {
            let ((worst, commits), _) = against_filter_at(&jitter, tau);
            assert!(worst < 1e-4, "τ = {tau}: {worst}");
            let per_s = (1.0f64).max(100.0 / tau);
            assert!((commits as f64 - 600.0 * per_s).abs() <= 1.0, "{commits}");
        }
        for (hz, commits_want) in [(3u64, 1500), (1, 600)] {
            let t_us: Vec<u64> = (0..=600 * hz).map(|k| 5_000 + k * 1_000_000 / hz).collect();
            let ((worst, commits), _) = against_filter_at(&t_us, 40.0);
            assert!(worst < 1e-4, "{hz} Hz: {worst}");
            assert_eq!(commits, commits_want, "{hz} Hz");
        }
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

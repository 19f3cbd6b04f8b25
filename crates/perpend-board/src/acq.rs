//! Acquisition logic: ADC counts → pin voltage → sensor signal (mA or V) →
//! distance [mm], NAMUR NE43 classification, and the per-channel stuck and
//! jump detectors.
//!
//! ## Counts to voltage
//!
//! The STM32G4 ADC is 12 bit; with hardware oversampling of ratio
//! `R = 2^os_log2` and right shift `S` the result is `Σ_R code >> S`, whose
//! full scale is `F = 4095·R / 2^S`. The pin voltage is
//! `V_pin = counts / F · V_ref` (ST's convention, full scale 4095 ↔ V_ref).
//! A result at or above `F` means the ADC clipped: the true signal is at
//! least the computed one.
//!
//! ## Pin voltage to signal and distance
//!
//! Current sensors: `I [mA] = 1000 · V_pin / R_shunt`. Voltage sensors:
//! `V = V_pin / ratio`. With the signal span `[sig_lo, sig_hi]` and
//! measuring range `[mm_lo, mm_hi]` of the channel's [`Transfer`]:
//! `x = (sig − sig_lo)/(sig_hi − sig_lo)`, `d = mm_lo + x·(mm_hi − mm_lo)`.
//!
//! ## Classification (NAMUR NE43, generalised to any span)
//!
//! In fractions `x` of the span (for 4-20 mA these are exactly NE43's
//! 3.6 / 3.8 / 20.5 / 21 mA):
//!
//! ```text
//! x < −0.025                 open loop       (< 3.6 mA)
//! −0.025 ≤ x < −0.0125       out of range    (3.6 ..< 3.8 mA)
//! −0.0125 ≤ x ≤ 1.03125      valid           (3.8 ..= 20.5 mA)
//! 1.03125 < x ≤ 1.0625       out of range    (20.5 ..= 21 mA)
//! x > 1.0625                 overcurrent     (> 21 mA)
//! ```
//!
//! The same fractions apply to voltage outputs: 0-10 V gives valid
//! −0.125..10.3125 V, out of range up to 10.625 V, over-voltage above (the
//! "overcurrent" bit). A 0-10 V output has no live zero, so an open input
//! (the divider pulls it to 0 V) reads as the start of the measuring range;
//! only the stuck detector catches it. Sensors with a live zero (e.g.
//! `sig_lo` = 1 V) get open-loop detection from the same thresholds. An ADC
//! result at full scale turns a "valid" class into out of range (the
//! reading is clipped).
//!
//! ## Stuck and jump detectors ([`Channel`])
//!
//! *Stuck*: a valid channel whose counts stay within `stuck_counts` of an
//! anchor value for `stuck_samples` consecutive samples (the anchor moves
//! whenever the counts leave the band, so slow drift does not count as
//! change). A live sensor's noise moves the oversampled counts every few
//! samples; a frozen output does not.
//!
//! *Jump*: the change of a channel's distance since the previous sample,
//! minus the median change of the other valid channels (so a rigid motion
//! of the head along the feed is not a jump), above `jump_mm`: the channel
//! is dropped for `jump_hold` samples (spatter, the edge of a hole under
//! one spot). A reading that stays off after the hold is caught by the
//! four-sensor residual check of the pipeline.

use perpend_core::params::{Acquisition, Frontend, Transfer};

/// NE43 class of a channel's signal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Class {
    /// Inside the measuring band (3.8..=20.5 mA).
    Valid,
    /// Saturated / out of the measuring range (3.6..3.8 or 20.5..=21 mA,
    /// or ADC clipped).
    OutOfRange,
    /// Below the failure limit (< 3.6 mA): broken wire, unpowered sensor.
    OpenLoop,
    /// Above the failure limit (> 21 mA): short circuit, sensor fault.
    Overcurrent,
}

impl Class {
    /// The status-word nibble bit of this class.
    pub const fn bit(self) -> u32 {
        match self {
            Class::Valid => crate::status::SENSOR_VALID,
            Class::OutOfRange => crate::status::SENSOR_OUT_OF_RANGE,
            Class::OpenLoop => crate::status::SENSOR_OPEN_LOOP,
            Class::Overcurrent => crate::status::SENSOR_OVERCURRENT,
        }
    }
}

/// One converted channel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Conversion {
    /// Sensor signal: mA (shunt) or V (divider).
    pub signal: f32,
    /// Distance by the transfer function [mm] (meaningful only when valid).
    pub mm: f32,
    /// NE43 class.
    pub class: Class,
}

/// Full-scale result `F = 4095·2^os_log2 / 2^os_shift` of the oversampled
/// ADC (module docs).
pub fn full_scale(acq: &Acquisition) -> f32 {
    let r = (1u32 << acq.os_log2.min(8)) as f32;
    let s = (1u32 << acq.os_shift.min(8)) as f32;
    4095.0 * r / s
}

/// Pin voltage [V] of an ADC result.
pub fn pin_volts(counts: u16, acq: &Acquisition) -> f32 {
    counts as f32 / full_scale(acq) * (acq.vref_mv as f32 * 1e-3)
}

/// Sensor signal (mA for a shunt, V for a divider) at pin voltage `v`.
pub fn signal_of_volts(v: f32, t: &Transfer) -> f32 {
    match t.frontend {
        Frontend::Shunt { ohm } => v / ohm * 1000.0,
        Frontend::Divider { ratio } => v / ratio,
    }
}

/// Fraction `x` of the signal span (module docs).
fn span_fraction(signal: f32, t: &Transfer) -> f32 {
    (signal - t.sig_lo) / (t.sig_hi - t.sig_lo)
}

/// NE43 class of a signal (thresholds in the module docs).
pub fn classify(signal: f32, t: &Transfer) -> Class {
    class_of_fraction(span_fraction(signal, t))
}

/// NE43 class of a span fraction `x` ([`classify`]).
fn class_of_fraction(x: f32) -> Class {
    if !(x >= -0.025) {
        // also catches NaN from a degenerate span
        Class::OpenLoop
    } else if x < -0.0125 {
        Class::OutOfRange
    } else if x <= 1.03125 {
        Class::Valid
    } else if x <= 1.0625 {
        Class::OutOfRange
    } else {
        Class::Overcurrent
    }
}

/// Converts and classifies one ADC result of a channel.
pub fn convert(counts: u16, t: &Transfer, acq: &Acquisition) -> Conversion {
    // The full scale and the span fraction once each (they were computed
    // twice: [`pin_volts`] and [`classify`] inlined; the same arithmetic).
    let fs = full_scale(acq);
    let signal = signal_of_volts(counts as f32 / fs * (acq.vref_mv as f32 * 1e-3), t);
    let x = span_fraction(signal, t);
    let mm = t.mm_lo + x * (t.mm_hi - t.mm_lo);
    let mut class = class_of_fraction(x);
    if class == Class::Valid && counts as f32 >= fs {
        class = Class::OutOfRange;
    }
    Conversion { signal, mm, class }
}

/// The ADC result a channel shows for sensor signal `signal` (mA or V),
/// rounded and clamped to the ADC's range: the inverse of [`convert`], for
/// simulated inputs (virtual board, tests).
pub fn counts_for_signal(signal: f32, t: &Transfer, acq: &Acquisition) -> u16 {
    let v = match t.frontend {
        Frontend::Shunt { ohm } => signal * ohm * 1e-3,
        Frontend::Divider { ratio } => signal * ratio,
    };
    let fs = full_scale(acq);
    let c = v / (acq.vref_mv as f32 * 1e-3) * fs;
    if !(c > 0.0) {
        0
    } else if c >= fs {
        fs as u16
    } else {
        (c + 0.5) as u16
    }
}

/// The sensor signal for distance `mm` (inverse transfer function).
pub fn signal_for_mm(mm: f32, t: &Transfer) -> f32 {
    t.sig_lo + (mm - t.mm_lo) / (t.mm_hi - t.mm_lo) * (t.sig_hi - t.sig_lo)
}

/// Per-channel detector state (stuck and jump).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Channel {
    anchor: Option<u16>,
    unchanged: u16,
    prev_mm: Option<f32>,
    hold: u16,
}

impl Channel {
    /// Forgets the history (a channel that left the valid band).
    pub fn reset(&mut self) {
        *self = Self::default();
    }

    /// Stuck detector on the raw counts of a valid sample. Returns true
    /// while the channel is stuck.
    pub fn stuck(&mut self, counts: u16, acq: &Acquisition) -> bool {
        if acq.stuck_samples == 0 {
            self.anchor = None;
            self.unchanged = 0;
            return false;
        }
        match self.anchor {
            Some(a) if counts.abs_diff(a) <= acq.stuck_counts => {
                self.unchanged = self.unchanged.saturating_add(1);
            }
            _ => {
                self.anchor = Some(counts);
                self.unchanged = 0;
            }
        }
        self.unchanged >= acq.stuck_samples
    }

    /// The change of the distance since the previous valid sample, if any.
    pub fn delta(&self, mm: f32) -> Option<f32> {
        self.prev_mm.map(|p| mm - p)
    }

    /// Jump detector: `excess` is this channel's change minus the common
    /// change of the others (None when this channel has no history).
    /// Records `mm` as the previous reading. Returns true while the channel
    /// is held out.
    pub fn jump(&mut self, mm: f32, excess: Option<f32>, acq: &Acquisition) -> bool {
        self.prev_mm = Some(mm);
        if acq.jump_mm > 0.0 {
            if let Some(e) = excess {
                if !(e.abs() <= acq.jump_mm) {
                    self.hold = acq.jump_hold.max(1);
                }
            }
        }
        if self.hold > 0 {
            self.hold -= 1;
            true
        } else {
            false
        }
    }
}

/// Median of `v` (the mean of the middle two for an even length; `None`
/// when empty). Insertion sort: meant for at most a handful of values.
pub fn median(v: &mut [f32]) -> Option<f32> {
    let n = v.len();
    if n == 0 {
        return None;
    }
    for i in 1..n {
        let mut j = i;
        while j > 0 && v[j - 1] > v[j] {
            v.swap(j - 1, j);
            j -= 1;
        }
    }
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// For each channel with a change in `deltas`, the common change of the
/// others: the [`median`] of their changes (0 when none has one), what the
/// jump detector subtracts. With all four changes finite (every sample of
/// a sound head) the four medians come from one sort: without the value
/// `x` of rank ≤ 1 the middle of the other three is the third smallest,
/// else the second (ties give equal values either way); ≈ 60
/// instructions instead of ≈ 300 for four sorts of three (issue 50
/// item 8). Otherwise by [`median`] itself.
pub fn common_changes(deltas: &[Option<f32>; 4]) -> [Option<f32>; 4] {
    if let [Some(a), Some(b), Some(c), Some(d)] = *deltas {
        if a.is_finite() && b.is_finite() && c.is_finite() && d.is_finite() {
            let mut s = [a, b, c, d];
            let mut swap = |i: usize, j: usize| {
                if s[i] > s[j] {
                    s.swap(i, j);
                }
            };
            // A sorting network for four values.
            swap(0, 1);
            swap(2, 3);
            swap(0, 2);
            swap(1, 3);
            swap(1, 2);
            let (s1, s2) = (s[1], s[2]);
            return [a, b, c, d].map(|x| Some(if x <= s1 { s2 } else { s1 }));
        }
    }
    core::array::from_fn(|i| {
        deltas[i]?;
        let mut others = [0.0f32; 4];
        let mut k = 0;
        for (j, dj) in deltas.iter().enumerate() {
            if let (true, Some(v)) = (j != i, dj) {
                others[k] = *v;
                k += 1;
            }
        }
        Some(median(&mut others[..k]).unwrap_or(0.0))
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use proptest::prelude::*;

    fn acq() -> Acquisition {
        Acquisition::factory()
    }

    /// 16× oversampling shifted back to the 12-bit scale.
    fn acq12() -> Acquisition {
        Acquisition {
            os_log2: 4,
            os_shift: 4,
            ..acq()
        }
    }

    #[test]
    fn counts_to_signal_golden() {
        // 16x oversampling, shift 4: full scale 4095, 3.3 V.
        let a = acq12();
        assert_relative_eq!(full_scale(&a), 4095.0);
        // factory: no shift, full scale 16 * 4095
        assert_relative_eq!(full_scale(&acq()), 65520.0);
        // 150 Ω: 12 mA -> 1.8 V -> 1.8/3.3*4095 = 2233.6 counts
        let t = Transfer::current(150.0, 20.0, 80.0);
        let c = convert(2234, &t, &a);
        assert_relative_eq!(
            c.signal,
            2234.0 / 4095.0 * 3.3 / 150.0 * 1000.0,
            epsilon = 1e-4
        );
        assert_eq!(c.class, Class::Valid);
        // mid-span: 12 mA -> 50 mm
        assert_relative_eq!(c.mm, 20.0 + (c.signal - 4.0) / 16.0 * 60.0, epsilon = 1e-4);
        assert_relative_eq!(c.mm, 50.0, epsilon = 0.02);
        // oversampling 256x, shift 4: full scale 65520
        let a2 = Acquisition {
            os_log2: 8,
            os_shift: 4,
            ..a
        };
        assert_relative_eq!(full_scale(&a2), 65520.0);
        let c2 = convert(32760, &t, &a2);
        assert_relative_eq!(c2.signal, 1.65 / 150.0 * 1000.0, epsilon = 1e-4);
    }

    #[test]
    fn ne43_bands_for_current() {
        let t = Transfer::current(150.0, 20.0, 80.0);
        let cases = [
            (0.0, Class::OpenLoop),
            (3.59, Class::OpenLoop),
            (3.61, Class::OutOfRange),
            (3.79, Class::OutOfRange),
            (3.81, Class::Valid),
            (4.0, Class::Valid),
            (20.0, Class::Valid),
            (20.49, Class::Valid),
            (20.51, Class::OutOfRange),
            (20.99, Class::OutOfRange),
            (21.01, Class::Overcurrent),
            (24.0, Class::Overcurrent),
        ];
        for (ma, want) in cases {
            assert_eq!(classify(ma, &t), want, "{ma} mA");
        }
    }

    #[test]
    fn voltage_scheme() {
        let t = Transfer::voltage(0.3, 10.0, 60.0);
        assert_eq!(classify(0.0, &t), Class::Valid);
        assert_eq!(classify(10.3, &t), Class::Valid);
        assert_eq!(classify(10.4, &t), Class::OutOfRange);
        assert_eq!(classify(10.7, &t), Class::Overcurrent);
        // live zero 1..10 V: an open input (0 V) is open loop
        let lz = Transfer { sig_lo: 1.0, ..t };
        assert_eq!(classify(0.0, &lz), Class::OpenLoop);
        // 5 V is half the span: 35 mm on a 10..60 mm sensor
        let a = acq();
        let c = convert(counts_for_signal(5.0, &t, &a), &t, &a);
        assert_relative_eq!(c.mm, 35.0, epsilon = 0.02);
    }

    #[test]
    fn adc_clipping_is_not_valid() {
        // 180 Ω shunt: full scale 3.3 V = 18.33 mA, inside the valid band.
        let t = Transfer::current(180.0, 20.0, 80.0);
        let a = acq12();
        assert_eq!(convert(4094, &t, &a).class, Class::Valid);
        assert_eq!(convert(4095, &t, &a).class, Class::OutOfRange);
        assert_eq!(convert(u16::MAX, &t, &a).class, Class::Overcurrent);
    }

    #[test]
    fn stuck_detector() {
        let a = Acquisition {
            stuck_samples: 5,
            stuck_counts: 1,
            ..acq()
        };
        let mut ch = Channel::default();
        // noise of ±1 count around 2000 stays in the anchor band ...
        let seq = [2000, 2001, 1999, 2000, 2001, 2000];
        let got: Vec<bool> = seq.iter().map(|&c| ch.stuck(c, &a)).collect();
        assert_eq!(got, [false, false, false, false, false, true]);
        assert!(ch.stuck(2000, &a));
        // ... a real change releases it
        assert!(!ch.stuck(2010, &a));
        // slow drift of one count per sample moves the anchor every 2 samples
        let mut ch = Channel::default();
        for k in 0..100u16 {
            assert!(!ch.stuck(1000 + k, &a));
        }
        // disabled
        let off = Acquisition {
            stuck_samples: 0,
            ..a
        };
        let mut ch = Channel::default();
        for _ in 0..100 {
            assert!(!ch.stuck(7, &off));
        }
    }

    #[test]
    fn jump_detector_holds_and_releases() {
        let a = Acquisition {
            jump_mm: 0.5,
            jump_hold: 3,
            ..acq()
        };
        let mut ch = Channel::default();
        assert!(!ch.jump(40.0, None, &a));
        assert!(!ch.jump(40.1, Some(0.1), &a));
        assert!(ch.jump(42.0, Some(1.9), &a)); // jump
        assert!(ch.jump(42.0, Some(0.0), &a)); // held
        assert!(ch.jump(42.0, Some(0.0), &a)); // held
        assert!(!ch.jump(42.0, Some(0.0), &a)); // released
        assert_eq!(ch.delta(42.5), Some(0.5));
        // NaN excess counts as a jump
        assert!(ch.jump(42.0, Some(f32::NAN), &a));
    }

    #[test]
    fn median_small() {
        assert_eq!(median(&mut []), None);
        assert_eq!(median(&mut [3.0]), Some(3.0));
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), Some(2.5));
    }

    proptest! {
        /// The one-sort common changes equal the median of the others'
        /// changes, channel by channel, ties and missing channels
        /// included (values on a coarse grid make ties frequent).
        #[test]
        fn common_changes_are_the_medians_of_the_others(
            v in proptest::array::uniform4(proptest::option::weighted(0.85, (-4i32..=4).prop_map(|k| k as f32 * 0.25))),
        ) {
            let got = common_changes(&v);
            for i in 0..4 {
                let mut others: Vec<f32> = (0..4).filter(|&j| j != i).filter_map(|j| v[j]).collect();
                let want = v[i].map(|_| median(&mut others).unwrap_or(0.0));
                prop_assert_eq!(got[i], want, "channel {} of {:?}", i, v);
            }
        }

        #[test]
        fn counts_round_trip_within_one_lsb(mm in 20.0f32..80.0, ohm in 100.0f32..160.0) {
            let t = Transfer::current(ohm, 20.0, 80.0);
            let a = acq();
            let c = convert(counts_for_signal(signal_for_mm(mm, &t), &t, &a), &t, &a);
            // half an LSB: 3.3 V / 4095 / ohm [mA] -> mm over 16 mA / 60 mm
            let lsb_mm = 3.3 / 4095.0 / ohm * 1000.0 / 16.0 * 60.0;
            prop_assert!((c.mm - mm).abs() <= 0.51 * lsb_mm + 1e-4);
            prop_assert_eq!(c.class, Class::Valid);
        }

        #[test]
        fn every_result_converts_to_finite_values(counts in any::<u16>(), log2 in 0u8..=8, sh in 0u8..=8) {
            let a = Acquisition { os_log2: log2, os_shift: sh.max(log2.saturating_sub(4)), ..acq() };
            let t = Transfer::voltage(0.25, 0.0, 100.0);
            let c = convert(counts, &t, &a);
            prop_assert!(c.signal.is_finite() && c.mm.is_finite());
        }
    }
}

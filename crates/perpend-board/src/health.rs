//! Board identity and health from the STM32G4's own registers and factory
//! calibration (issue 11 items 7 and 9): the reset cause (RCC_CSR), VREF+
//! from the internal reference (VREFINT), the die temperature (TS_CAL1/2),
//! the flash layout the storage needs (FLASH_OPTR.DBANK, the flash size
//! register), the worst main-loop time (DWT CYCCNT) and the stack high-water
//! mark of a painted stack.
//!
//! Pure arithmetic on register values; the firmware reads the registers.
//! Equations:
//! * VREF+ = 3000 mV · VREFINT_CAL / VREFINT_DATA (RM0440 §21.4.34; the
//!   calibration value is taken at VREF+ = 3.0 V, 30 °C);
//! * T = 30 °C + (TS_DATA·VREF+/3.0 V − TS_CAL1) · 100 °C / (TS_CAL2 −
//!   TS_CAL1) (RM0440 §21.4.32; TS_CAL1 at 30 °C, TS_CAL2 at 130 °C, both at
//!   VREF+ = 3.0 V);
//! * an ADC count at the measured VREF+ is rescaled to the assumed one by
//!   VREF+ / VREF+assumed.
//!
//! Limits: 12-bit factory values; results of an oversampled conversion
//! are first divided by the oversampling gain (2^ratio / 2^shift).

/// Errors of this module.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HealthError {
    /// The flash is in single-bank mode (FLASH_OPTR.DBANK = 0): the storage
    /// pages and read-while-write assume two banks of 2 KiB pages.
    SingleBank,
    /// The flash is smaller than the storage range needs [KiB].
    FlashTooSmall(u16),
}

/// EMCY code after a watchdog reset (CiA 301 0x6010 "software reset
/// (watchdog)"), data `[RCC_CSR flags >> 24, 0, 0, 0, 0]`.
pub const EMCY_WATCHDOG_RESET: u16 = 0x6010;

/// Calibration reference voltage of VREFINT_CAL, TS_CAL1, TS_CAL2 [mV].
pub const CAL_VREF_MV: f32 = 3000.0;
/// Plausible VREF+ [mV]: the ADC's operating range (datasheet: 1.62 V to
/// VDDA ≤ 3.6 V).
pub const VREF_RANGE_MV: core::ops::RangeInclusive<f32> = 1620.0..=3600.0;

/// The reset flags of RCC_CSR (bits 25..31) as one byte (CSR >> 24).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ResetFlags(pub u8);

/// The main cause of a reset, most significant first.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResetCause {
    /// Power-on or brown-out (BORRSTF; the pin flag is set too).
    PowerOn,
    /// Independent watchdog (IWDGRSTF).
    IndependentWatchdog,
    /// Window watchdog (WWDGRSTF).
    WindowWatchdog,
    /// Software reset (SFTRSTF: NVIC system reset, e.g. a debugger or a
    /// jump to the bootloader).
    Software,
    /// Option byte loading (OBLRSTF).
    OptionLoad,
    /// Illegal low-power entry (LPWRRSTF).
    LowPower,
    /// The NRST pin alone (PINRSTF).
    Pin,
    /// No flag set.
    Unknown,
}

impl ResetFlags {
    /// OBLRSTF (RCC_CSR bit 25) in the byte.
    pub const OPTION_LOAD: u8 = 1 << 1;
    /// PINRSTF (bit 26).
    pub const PIN: u8 = 1 << 2;
    /// BORRSTF (bit 27).
    pub const BROWN_OUT: u8 = 1 << 3;
    /// SFTRSTF (bit 28).
    pub const SOFTWARE: u8 = 1 << 4;
    /// IWDGRSTF (bit 29).
    pub const IWDG: u8 = 1 << 5;
    /// WWDGRSTF (bit 30).
    pub const WWDG: u8 = 1 << 6;
    /// LPWRRSTF (bit 31).
    pub const LOW_POWER: u8 = 1 << 7;

    /// From the RCC_CSR value.
    pub const fn from_csr(csr: u32) -> Self {
        Self((csr >> 24) as u8 & 0xFE)
    }

    /// The main cause (a watchdog wins over the pin flag it also sets).
    pub const fn cause(self) -> ResetCause {
        let f = self.0;
        if f & Self::BROWN_OUT != 0 {
            ResetCause::PowerOn
        } else if f & Self::IWDG != 0 {
            ResetCause::IndependentWatchdog
        } else if f & Self::WWDG != 0 {
            ResetCause::WindowWatchdog
        } else if f & Self::SOFTWARE != 0 {
            ResetCause::Software
        } else if f & Self::OPTION_LOAD != 0 {
            ResetCause::OptionLoad
        } else if f & Self::LOW_POWER != 0 {
            ResetCause::LowPower
        } else if f & Self::PIN != 0 {
            ResetCause::Pin
        } else {
            ResetCause::Unknown
        }
    }

    /// Whether a watchdog caused the reset (EMCY [`EMCY_WATCHDOG_RESET`]).
    pub const fn is_watchdog(self) -> bool {
        matches!(
            self.cause(),
            ResetCause::IndependentWatchdog | ResetCause::WindowWatchdog
        )
    }
}

/// Oversampling gain of a result: 2^ratio / 2^shift.
pub fn os_gain(os_log2: u8, os_shift: u8) -> f32 {
    (1u32 << os_log2.min(8)) as f32 / (1u32 << os_shift.min(8)) as f32
}

/// VREF+ [mV] from the VREFINT result `raw` (oversampled with `gain`) and
/// the factory VREFINT_CAL; `None` when either is 0 or the result is
/// outside [`VREF_RANGE_MV`].
pub fn vref_mv(vrefint_cal: u16, raw: u16, gain: f32) -> Option<f32> {
    let data = raw as f32 / gain;
    if vrefint_cal == 0 || !(data > 0.0) {
        return None;
    }
    let v = CAL_VREF_MV * vrefint_cal as f32 / data;
    VREF_RANGE_MV.contains(&v).then_some(v)
}

/// Rescales an ADC count taken at VREF+ = `measured_mv` to the count the
/// pipeline expects at `assumed_mv` (saturating at `u16::MAX`).
pub fn correct_count(count: u16, measured_mv: f32, assumed_mv: f32) -> u16 {
    if !(assumed_mv > 0.0) || !(measured_mv > 0.0) {
        return count;
    }
    let c = count as f32 * measured_mv / assumed_mv + 0.5;
    if c >= u16::MAX as f32 {
        u16::MAX
    } else {
        c as u16
    }
}

/// Die temperature [°C] from the sensor's result `raw` (oversampled with
/// `gain`) at VREF+ = `vref_mv`, with the factory TS_CAL1 (30 °C) and
/// TS_CAL2 (130 °C); `None` when the calibration is implausible.
pub fn die_temp_c(raw: u16, gain: f32, vref_mv: f32, ts_cal1: u16, ts_cal2: u16) -> Option<f32> {
    if ts_cal2 <= ts_cal1 || !(gain > 0.0) || !(vref_mv > 0.0) {
        return None;
    }
    let at_cal = raw as f32 / gain * (vref_mv / CAL_VREF_MV);
    Some((at_cal - ts_cal1 as f32) * 100.0 / (ts_cal2 - ts_cal1) as f32 + 30.0)
}

/// Checks the flash layout the storage needs: dual-bank mode and at least
/// `need_kib` of flash (the size register FLASH_SIZE, in KiB).
///
/// # Errors
/// [`HealthError::SingleBank`], [`HealthError::FlashTooSmall`].
pub fn check_flash(dbank: bool, size_kib: u16, need_kib: u16) -> Result<(), HealthError> {
    if size_kib < need_kib {
        return Err(HealthError::FlashTooSmall(size_kib));
    }
    if !dbank {
        return Err(HealthError::SingleBank);
    }
    Ok(())
}

/// The worst main-loop time from a free-running 32-bit cycle counter.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct LoopTimer {
    worst: u32,
}

impl LoopTimer {
    /// Records one loop turn from `start` to `end` (counter values; the
    /// counter may wrap once). Returns true on a new worst.
    pub fn record(&mut self, start: u32, end: u32) -> bool {
        let d = end.wrapping_sub(start);
        if d > self.worst {
            self.worst = d;
            true
        } else {
            false
        }
    }

    /// The worst turn so far [cycles].
    pub fn worst(&self) -> u32 {
        self.worst
    }
}

/// Stack paint pattern.
pub const STACK_PAINT: u32 = 0xC0FF_EE55;

/// Bytes of a painted stack region used so far: `words` is the region from
/// its lowest address up, painted with [`STACK_PAINT`]; the stack grows
/// down, so the untouched words are at the start.
pub fn stack_used(words: impl ExactSizeIterator<Item = u32>) -> usize {
    let len = words.len();
    let untouched = words.take_while(|&w| w == STACK_PAINT).count();
    (len - untouched) * 4
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn reset_causes_from_csr() {
        // power-on: BORRSTF + PINRSTF (RM0440 §7.4.29 reset value 0x0C00_0000)
        assert_eq!(
            ResetFlags::from_csr(0x0C00_0000).cause(),
            ResetCause::PowerOn
        );
        // IWDG also sets the pin flag
        let wd = ResetFlags::from_csr((1 << 29) | (1 << 26));
        assert_eq!(wd.cause(), ResetCause::IndependentWatchdog);
        assert!(wd.is_watchdog());
        assert_eq!(wd.0, 0x24);
        assert_eq!(
            ResetFlags::from_csr((1 << 28) | (1 << 26)).cause(),
            ResetCause::Software
        );
        assert!(!ResetFlags::from_csr(1 << 28).is_watchdog());
        assert_eq!(ResetFlags::from_csr(1 << 26).cause(), ResetCause::Pin);
        assert_eq!(
            ResetFlags::from_csr(1 << 30).cause(),
            ResetCause::WindowWatchdog
        );
        assert_eq!(ResetFlags::from_csr(1 << 31).cause(), ResetCause::LowPower);
        assert_eq!(
            ResetFlags::from_csr(1 << 25).cause(),
            ResetCause::OptionLoad
        );
        // other CSR bits (LSION, RMVF) do not count
        assert_eq!(
            ResetFlags::from_csr(0x0080_0001).cause(),
            ResetCause::Unknown
        );
    }

    #[test]
    fn vref_from_vrefint() {
        // a typical VREFINT_CAL of 1655 counts (1.212 V at 3.0 V)
        let cal = 1655;
        // at VREF+ = 3.3 V the reading is 1655·3.0/3.3 = 1504.5; 16×
        // oversampling without shift: ×16
        let v = vref_mv(cal, (1504.5f32 * 16.0) as u16, os_gain(4, 0)).unwrap();
        assert!((v - 3300.0).abs() < 0.5, "{v}");
        // at 3.0 V exactly the calibration value
        assert_eq!(vref_mv(cal, cal, 1.0), Some(3000.0));
        // implausible: no calibration, 0 reading, VREF+ > 3.6 V
        assert_eq!(vref_mv(0, 1500, 1.0), None);
        assert_eq!(vref_mv(cal, 0, 1.0), None);
        assert_eq!(vref_mv(cal, 1300, 1.0), None);
    }

    #[test]
    fn count_correction_and_its_size() {
        // VREF+ 1 % low (3.267 V): a count read at 3.267 V is 1 % too
        // high for 3.3 V; the corrected one is 1 % lower.
        let c = correct_count(40_000, 3267.0, 3300.0);
        assert_eq!(c, 39_600);
        assert_eq!(correct_count(65_535, 3600.0, 3300.0), u16::MAX);
        assert_eq!(correct_count(1234, 3300.0, 0.0), 1234);
    }

    #[test]
    fn die_temperature_at_the_calibration_points() {
        let (c1, c2) = (1034, 1375);
        let t = |raw: u16, g: f32, v: f32| die_temp_c(raw, g, v, c1, c2).unwrap();
        assert!((t(c1, 1.0, 3000.0) - 30.0).abs() < 1e-4);
        assert!((t(c2, 1.0, 3000.0) - 130.0).abs() < 1e-4);
        // the same 30 °C read at 3.3 V with 16× oversampling
        let raw = (c1 as f32 * 3000.0 / 3300.0 * 16.0).round() as u16;
        assert!((t(raw, 16.0, 3300.0) - 30.0).abs() < 0.05);
        assert_eq!(die_temp_c(1000, 1.0, 3000.0, c2, c1), None);
    }

    #[test]
    fn flash_layout() {
        assert_eq!(check_flash(true, 512, 512), Ok(()));
        assert_eq!(check_flash(false, 512, 512), Err(HealthError::SingleBank));
        assert_eq!(
            check_flash(true, 256, 512),
            Err(HealthError::FlashTooSmall(256))
        );
    }

    #[test]
    fn loop_timer_keeps_the_worst_across_a_wrap() {
        let mut l = LoopTimer::default();
        assert!(l.record(100, 1100));
        assert!(!l.record(5000, 5500));
        assert!(l.record(u32::MAX - 99, 2000)); // wrapped: 2100 cycles
        assert_eq!(l.worst(), 2100);
    }

    fn booted() -> crate::app::App<crate::storage::SeqStore<crate::storage::HostFlash>> {
        let mut app =
            crate::app::App::new(crate::storage::host_store(crate::storage::HostFlash::new()));
        app.poll(0, &mut |_| {});
        app
    }

    fn emcy_codes(frames: &[perpend_can::Frame]) -> std::vec::Vec<u16> {
        frames
            .iter()
            .filter(|f| (0x81..=0xFF).contains(&f.id))
            .map(|f| u16::from_le_bytes([f.data[0], f.data[1]]))
            .collect()
    }

    #[test]
    fn a_watchdog_reset_is_reported_by_object_and_emcy() {
        let mut app = booted();
        let flags = ResetFlags::from_csr((1 << 29) | (1 << 26));
        app.report_reset(flags);
        let mut out = std::vec::Vec::new();
        app.poll(1000, &mut |f| out.push(f));
        assert_eq!(emcy_codes(&out), [EMCY_WATCHDOG_RESET, 0]);
        let e = out.iter().find(|f| f.data[..2] == [0x10, 0x60]).unwrap();
        assert_eq!(e.data[3], 0x24);
        assert_eq!(app.device().read_u32(0x200B, 1), Some(0x24));
        // a power-on reset: the object only
        let mut app = booted();
        app.report_reset(ResetFlags::from_csr(0x0C00_0000));
        let mut out = std::vec::Vec::new();
        app.poll(1000, &mut |f| out.push(f));
        assert_eq!(emcy_codes(&out), std::vec::Vec::<u16>::new());
        assert_eq!(app.device().read_u32(0x200B, 1), Some(0x0C));
    }

    #[test]
    fn die_temperature_and_health_reach_the_dictionary() {
        let mut app = booted();
        let unknown = perpend_can::od::DIE_TEMP_UNKNOWN;
        assert_eq!(app.device().read_f32(0x200A, 0), Some(unknown));
        let s = crate::pipeline::Sample {
            temp_c: Some(41.5),
            ..Default::default()
        };
        app.on_sample(&s, 1000);
        app.poll(2000, &mut |_| {});
        assert_eq!(app.device().read_f32(0x200A, 0), Some(41.5));
        // a sample without temperature keeps the last value
        app.on_sample(&crate::pipeline::Sample::default(), 3000);
        app.poll(4000, &mut |_| {});
        assert_eq!(app.device().read_f32(0x200A, 0), Some(41.5));
        app.set_health(123_456, 2048, 3297);
        let h: std::vec::Vec<_> = (2..=4).map(|s| app.device().read_u32(0x200B, s)).collect();
        assert_eq!(h, [Some(123_456), Some(2048), Some(3297)]);
    }

    #[test]
    fn the_bootloader_command_is_honoured_in_pre_operational_only() {
        let sdo = |app: &mut crate::app::App<_>, v: u8| {
            let f = perpend_can::Frame::new(0x620, &[0x2F, 0x00, 0x25, 0, v, 0, 0, 0]);
            let mut out = std::vec::Vec::new();
            app.handle(&f, 100, &mut |o| out.push(o));
            out.iter().find(|o| o.id == 0x5A0).map(|o| o.data[0])
        };
        let mut app = booted();
        assert_eq!(sdo(&mut app, perpend_can::od::CMD_BOOTLOADER), Some(0x60));
        assert!(app.take_bootloader_request());
        assert!(!app.take_bootloader_request());
        // operational: written (it is the command object) but not honoured
        app.handle(&perpend_can::Frame::new(0, &[1, 0x20]), 200, &mut |_| {});
        assert_eq!(app.device().nmt_state(), perpend_can::NmtState::Operational);
        assert_eq!(sdo(&mut app, perpend_can::od::CMD_BOOTLOADER), Some(0x60));
        assert!(!app.take_bootloader_request());
        // other values are refused as before
        assert_eq!(sdo(&mut app, 0xB1), Some(0x80));
    }

    proptest! {
        #[test]
        fn stack_used_counts_the_touched_top(len in 1usize..64, used in 0usize..64) {
            let used = used.min(len);
            let mut w = vec![STACK_PAINT; len];
            for x in w.iter_mut().skip(len - used) {
                *x = 0x1234_5678;
            }
            prop_assert_eq!(stack_used(w.iter().copied()), used * 4);
        }
    }
}

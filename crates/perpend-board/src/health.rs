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

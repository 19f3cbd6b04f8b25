//! Duration of one ADC scan, and the smallest sample period (object 0x2300
//! sub 1) an oversampling ratio (sub 2) allows.
//!
//! The firmware's ADC1 (see `src/main.rs`, docs/firmware.md) runs from
//! SYSCLK / 4 = **42.5 MHz** ([`ADC_CLOCK_HZ`]) and converts, per trigger,
//! the four sensor inputs at **47.5** ADC clock cycles of sampling each and
//! the temperature sensor at **247.5** (its 5 µs minimum, datasheet
//! t_S_temp), every conversion followed by **12.5** cycles of 12-bit
//! successive approximation (RM0440 §21.4.16). With regular oversampling of
//! ratio N (ROVSM continued, TROVS = 0: all N conversions of a channel
//! follow the one trigger, §21.4.30) every channel is converted N times in a
//! row:
//!
//! ```text
//! scan(N) = N · (4 · (47.5 + 12.5) + (247.5 + 12.5)) / 42.5 MHz = N · 11.765 µs
//! ```
//!
//! | oversampling | 1 | 2 | 4 | 8 | 16 | 32 | 64 | 128 | 256 |
//! |---|---|---|---|---|---|---|---|---|---|
//! | scan [µs] | 11.8 | 23.5 | 47.1 | 94.1 | 188.2 | 376.5 | 752.9 | 1505.9 | 3011.8 |
//! | shortest period [µs] | 100 | 100 | 100 | 100 | 189 | 377 | 753 | 1506 | 3012 |
//!
//! A trigger that arrives while a scan is still converting is ignored by
//! the ADC (§21.4.19), so a period shorter than the scan would silently
//! halve the sample rate: the object dictionary refuses such a combination
//! (SDO abort 0x06090030, see `perpend_can::Defaults::adc_scan_ns`) and
//! [`crate::app::params_from_device`] treats one as an invalid
//! configuration.
//!
//! Limits: the model has no margin for the trigger latency (a few ADC
//! clocks) nor for the CPU time of the pipeline (≈ 25 µs per sample);
//! both fit into the 100 µs lower limit of the period.

/// ADC kernel clock: SYSCLK 170 MHz / 4 \[Hz\].
pub const ADC_CLOCK_HZ: u64 = 42_500_000;
/// Sampling time of each sensor input, in half ADC clock cycles (47.5).
pub const SENSOR_SAMPLE_HALF_CYCLES: u64 = 95;
/// Sampling time of the temperature sensor, in half cycles (247.5).
pub const TEMP_SAMPLE_HALF_CYCLES: u64 = 495;
/// Successive-approximation time of a 12-bit conversion, in half cycles
/// (12.5).
pub const CONVERSION_HALF_CYCLES: u64 = 25;
/// Sensor channels per scan.
pub const SENSOR_CHANNELS: u64 = 4;

/// Half ADC clock cycles of one scan without oversampling.
pub const SCAN_HALF_CYCLES: u64 = SENSOR_CHANNELS
    * (SENSOR_SAMPLE_HALF_CYCLES + CONVERSION_HALF_CYCLES)
    + TEMP_SAMPLE_HALF_CYCLES
    + CONVERSION_HALF_CYCLES;

/// Duration of one scan without oversampling, rounded up \[ns\]
/// (11,765 ns): the value the board gives the object dictionary.
pub const SCAN_NS: u32 = scan_ns(1) as u32;

/// Duration of one scan at oversampling ratio `ratio`, rounded up \[ns\].
pub const fn scan_ns(ratio: u32) -> u64 {
    let num = ratio as u64 * SCAN_HALF_CYCLES * 1_000_000_000;
    let den = 2 * ADC_CLOCK_HZ;
    num.div_ceil(den)
}

/// Whether a scan at oversampling `ratio` fits into `period_us`.
pub const fn fits(period_us: u32, ratio: u32) -> bool {
    scan_ns(ratio) <= period_us as u64 * 1000
}

/// The smallest period \[µs\] a scan at oversampling `ratio` fits into.
pub const fn min_period_us(ratio: u32) -> u32 {
    scan_ns(ratio).div_ceil(1000) as u32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scan_time_of_the_documented_configuration() {
        // 4 × 60 + 260 = 500 cycles at 42.5 MHz.
        assert_eq!(SCAN_HALF_CYCLES, 1000);
        assert_eq!(SCAN_NS, 11_765);
        assert_eq!(scan_ns(16), 188_236);
        assert_eq!(scan_ns(256), 3_011_765);
        assert_eq!(min_period_us(16), 189);
        assert_eq!(min_period_us(8), 95);
    }

    #[test]
    fn fits_is_exact_at_the_limit() {
        for k in 0..=8 {
            let r = 1u32 << k;
            let p = min_period_us(r);
            assert!(fits(p, r), "{r}");
            assert!(!fits(p - 1, r), "{r}");
        }
        // the factory setting: 1 kHz, 16×
        assert!(fits(1000, 16));
        assert!(!fits(100, 16));
        assert!(fits(100, 8));
    }
}

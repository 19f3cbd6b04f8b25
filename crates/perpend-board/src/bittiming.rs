//! Nominal bit timing of the FDCAN for the four CANopen bit rates of
//! object 0x2400 sub 2, instead of the driver's own calculation.
//!
//! The FDCAN kernel clock is the 24 MHz HSE crystal
//! ([`FDCAN_KERNEL_HZ`]). Every rate uses **24 time quanta** per bit, the
//! **sample point at 87.5 %** (CiA 301 / CiA 303-1 recommendation: the
//! sync quantum and 20 in segment 1 are 21 of 24) and a
//! **resynchronisation jump width of 3 tq** (= phase segment 2, the
//! largest allowed); lower rates scale the prescaler only, so the sample
//! point and the SJW as a fraction of the bit stay the same:
//!
//! | bit rate | prescaler | tq | tq/bit | seg 1 | seg 2 | SJW | sample point | NBTP |
//! |---|---|---|---|---|---|---|---|---|
//! | 1000 kbit/s | 1 | 41.7 ns | 24 | 20 | 3 | 3 | 87.5 % | 0x0400_1302 |
//! | 500 kbit/s | 2 | 83.3 ns | 24 | 20 | 3 | 3 | 87.5 % | 0x0401_1302 |
//! | 250 kbit/s | 4 | 167 ns | 24 | 20 | 3 | 3 | 87.5 % | 0x0403_1302 |
//! | 125 kbit/s | 8 | 333 ns | 24 | 20 | 3 | 3 | 87.5 % | 0x0407_1302 |
//!
//! Oscillator tolerance these settings allow (Bosch CAN 2.0 conditions):
//! min(SJW / (20·24), min(seg 1, seg 2) / (2·(13·24 − seg 2))) = 0.49 %,
//! far above a crystal's 50 ppm.
//!
//! [`nominal`] computes the timing for any kernel clock (the largest number
//! of quanta per bit, 8..=25, that divides the clock exactly); the table is
//! what it gives for 24 MHz and is checked against it.
//!
//! Limits: classic CAN nominal timing only (no CAN FD data phase).

use perpend_core::params::Bitrate;
use perpend_core::Error;

/// The FDCAN kernel clock of the board: the HSE crystal \[Hz\].
pub const FDCAN_KERNEL_HZ: u32 = 24_000_000;

/// Nominal bit timing in time quanta (the FDCAN_NBTP fields are these
/// values minus one).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BitTiming {
    /// Kernel clock divider: one time quantum = `prescaler` kernel clocks
    /// (NBRP + 1, 1..=512).
    pub prescaler: u16,
    /// Propagation + phase segment 1 \[tq\] (NTSEG1 + 1, 2..=256).
    pub seg1: u16,
    /// Phase segment 2 \[tq\] (NTSEG2 + 1, 2..=128).
    pub seg2: u8,
    /// Resynchronisation jump width \[tq\] (NSJW + 1, 1..=128, ≤ `seg2`).
    pub sjw: u8,
}

/// The board's table (kernel clock [`FDCAN_KERNEL_HZ`]), in the order
/// 1000, 500, 250, 125 kbit/s; see the module docs.
pub const TABLE_24MHZ: [(Bitrate, BitTiming); 4] = [
    (Bitrate::M1, timing24(1)),
    (Bitrate::K500, timing24(2)),
    (Bitrate::K250, timing24(4)),
    (Bitrate::K125, timing24(8)),
];

const fn timing24(prescaler: u16) -> BitTiming {
    BitTiming {
        prescaler,
        seg1: 20,
        seg2: 3,
        sjw: 3,
    }
}

impl BitTiming {
    /// Time quanta per bit (sync segment + `seg1` + `seg2`).
    pub const fn quanta(&self) -> u32 {
        1 + self.seg1 as u32 + self.seg2 as u32
    }

    /// The bit rate at kernel clock `kernel_hz` \[bit/s\] (rounded down;
    /// exact when the timing came from [`nominal`]).
    pub const fn bit_rate(&self, kernel_hz: u32) -> u32 {
        kernel_hz / (self.prescaler as u32 * self.quanta())
    }

    /// Sample point in per mille of the bit (875 = 87.5 %), rounded down.
    pub const fn sample_point_permille(&self) -> u32 {
        (1 + self.seg1 as u32) * 1000 / self.quanta()
    }

    /// The FDCAN_NBTP register value (RM0440 §44.4.8): NSJW\[31:25\],
    /// NBRP\[24:16\], NTSEG1\[15:8\], NTSEG2\[6:0\], each field = value − 1.
    pub const fn nbtp(&self) -> u32 {
        ((self.sjw as u32 - 1) << 25)
            | ((self.prescaler as u32 - 1) << 16)
            | ((self.seg1 as u32 - 1) << 8)
            | (self.seg2 as u32 - 1)
    }

    /// Whether every field fits its NBTP range and SJW ≤ phase segment 2.
    pub const fn fits_nbtp(&self) -> bool {
        self.prescaler >= 1
            && self.prescaler <= 512
            && self.seg1 >= 2
            && self.seg1 <= 256
            && self.seg2 >= 2
            && self.seg2 <= 128
            && self.sjw >= 1
            && self.sjw <= 128
            && self.sjw <= self.seg2
    }
}

/// The board's timing for `b` (the row of [`TABLE_24MHZ`]).
pub const fn for_board(b: Bitrate) -> BitTiming {
    match b {
        Bitrate::M1 => TABLE_24MHZ[0].1,
        Bitrate::K500 => TABLE_24MHZ[1].1,
        Bitrate::K250 => TABLE_24MHZ[2].1,
        Bitrate::K125 => TABLE_24MHZ[3].1,
    }
}

/// Nominal timing for `bitrate` from a kernel clock of `kernel_hz`: the
/// largest number of quanta per bit in 8..=25 that gives the rate exactly,
/// sample point 87.5 % (rounded to whole quanta), SJW = phase segment 2.
///
/// # Errors
/// [`Error::OutOfRange`] when no quanta count gives the rate exactly with a
/// prescaler of at most 512.
pub fn nominal(kernel_hz: u32, bitrate: Bitrate) -> Result<BitTiming, Error> {
    let bps = bitrate.bps();
    if bps == 0 || !kernel_hz.is_multiple_of(bps) {
        return Err(Error::OutOfRange("CAN kernel clock for the bit rate"));
    }
    let clocks_per_bit = kernel_hz / bps;
    for q in (8..=25u32).rev() {
        let prescaler = clocks_per_bit / q;
        if !clocks_per_bit.is_multiple_of(q) || !(1..=512).contains(&prescaler) {
            continue;
        }
        // 1 + seg1 = round(0.875 q)
        let before_sample = (7 * q + 4) / 8;
        let seg2 = q - before_sample;
        let t = BitTiming {
            prescaler: prescaler as u16,
            seg1: (before_sample - 1) as u16,
            seg2: seg2 as u8,
            sjw: seg2 as u8,
        };
        if t.fits_nbtp() {
            return Ok(t);
        }
    }
    Err(Error::OutOfRange("CAN kernel clock for the bit rate"))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    const RATES: [Bitrate; 4] = [Bitrate::M1, Bitrate::K500, Bitrate::K250, Bitrate::K125];

    #[test]
    fn table_rates_are_exact_with_the_sample_point_at_87_5_percent() {
        for (b, t) in TABLE_24MHZ {
            assert_eq!(t.quanta(), 24, "{b:?}");
            assert_eq!(t.prescaler as u32 * 24 * b.bps(), FDCAN_KERNEL_HZ, "{b:?}");
            assert_eq!(t.bit_rate(FDCAN_KERNEL_HZ), b.bps());
            assert_eq!(t.sample_point_permille(), 875);
            assert_eq!((1 + t.seg1 as u32) * 8, 7 * t.quanta(), "exactly 7/8");
            assert_eq!(t.sjw, 3);
            assert!(t.sjw <= t.seg2);
            assert!(t.fits_nbtp(), "{b:?}");
            assert_eq!(for_board(b), t);
        }
    }

    #[test]
    fn table_is_what_the_calculation_gives() {
        for (b, t) in TABLE_24MHZ {
            assert_eq!(nominal(FDCAN_KERNEL_HZ, b).unwrap(), t, "{b:?}");
        }
    }

    #[test]
    fn nbtp_fields_are_in_their_register_ranges() {
        for (_, t) in TABLE_24MHZ {
            let r = t.nbtp();
            let nsjw = r >> 25;
            let nbrp = (r >> 16) & 0x1FF;
            let ntseg1 = (r >> 8) & 0xFF;
            let ntseg2 = r & 0x7F;
            assert_eq!(r & 0x80, 0, "reserved bit 7");
            assert!((1..=512).contains(&(nbrp + 1)));
            assert!((2..=256).contains(&(ntseg1 + 1)));
            assert!((2..=128).contains(&(ntseg2 + 1)));
            assert!((1..=128).contains(&(nsjw + 1)));
            assert!(nsjw <= ntseg2);
        }
        assert_eq!(for_board(Bitrate::M1).nbtp(), 0x0400_1302);
        assert_eq!(for_board(Bitrate::K125).nbtp(), 0x0407_1302);
    }

    #[test]
    fn other_kernel_clocks_are_exact_or_refused() {
        for clock in [8_000_000, 16_000_000, 40_000_000, 80_000_000, 170_000_000] {
            for b in RATES {
                if let Ok(t) = nominal(clock, b) {
                    assert_eq!(t.bit_rate(clock) * t.prescaler as u32 * t.quanta(), clock);
                    assert_eq!(t.bit_rate(clock), b.bps());
                    assert!(t.fits_nbtp());
                    assert!((850..=900).contains(&t.sample_point_permille()));
                }
            }
        }
        // 7 MHz cannot make 1 Mbit/s with 8..25 quanta; 1 MHz not 125 k × 8+.
        assert!(nominal(7_000_000, Bitrate::M1).is_err());
        assert!(nominal(999_999, Bitrate::K125).is_err());
        assert_eq!(nominal(16_000_000, Bitrate::M1).unwrap().quanta(), 16);
    }
}

//! The CAN bus state from one read of the FDCAN protocol status register
//! per tick ([`BusMonitor`]), and the main loop's receive budget
//! ([`RxBudget`]).
//!
//! ## PSR (RM0440 §44.4.14)
//!
//! PSR.LEC (last error code, bits 2:0) is set to 7 ("no change") by every
//! read of PSR, so two readers undercount: the bus-off poll read PSR on
//! every tick and the receive path read it again for LEC (and
//! embassy-stm32's `CanRx::read` reads it whenever both FIFOs are empty).
//! The firmware now reads PSR in one place, [`BusMonitor::tick`], once per
//! 1 ms tick, and both users (the bus-error counter, the bus-off state
//! that gates the watchdog and raises EMCY 0x8140) are fed from that read.
//! LEC keeps only the last error: more than one error between two ticks
//! counts as one (a lower bound, as any LEC-based count).
//!
//! ## Receive budget
//!
//! Under a sustained receive flood the frame source is always ready; the
//! firmware's select polls the tick first (it pets the IWDG and checks
//! bus-off) and the frame source last, and [`RxBudget`] stops taking
//! frames after [`RX_PER_TICK`] per tick (the rest waits in the RAM ring),
//! so each tick is serviced within one frame's work after it is due.

/// PSR.LEC: no error.
const LEC_NONE: u32 = 0;
/// PSR.LEC: no change since the last read.
const LEC_NO_CHANGE: u32 = 7;
/// PSR.EP: error passive.
const PSR_EP: u32 = 1 << 5;
/// PSR.BO: bus-off.
const PSR_BO: u32 = 1 << 7;

/// The register the monitor reads (every read sets PSR.LEC to 7).
pub trait PsrRead {
    /// Reads FDCAN_PSR.
    fn read_psr(&mut self) -> u32;
}

/// The controller's error state (PSR.BO, PSR.EP).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BusState {
    /// Error active.
    Active,
    /// Error passive.
    Passive,
    /// Bus-off.
    BusOff,
}

/// A change of the bus-off state seen by [`BusMonitor::tick`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BusEvent {
    /// Nothing changed.
    None,
    /// The controller went bus-off.
    BusOff,
    /// The controller left bus-off (the driver's automatic recovery).
    Recovered,
}

/// Bus errors and bus-off state from one PSR read per tick.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BusMonitor {
    errors: u32,
    bus_off_since_us: Option<u64>,
}

impl BusMonitor {
    /// No error seen, not bus-off.
    pub const fn new() -> Self {
        Self {
            errors: 0,
            bus_off_since_us: None,
        }
    }

    /// Reads PSR once and feeds both users from it.
    pub fn tick(&mut self, r: &mut impl PsrRead, now_us: u64) -> BusEvent {
        self.on_psr(r.read_psr(), now_us)
    }

    /// Takes one PSR value: counts its LEC, follows BO.
    pub fn on_psr(&mut self, psr: u32, now_us: u64) -> BusEvent {
        let lec = psr & 0b111;
        if lec != LEC_NONE && lec != LEC_NO_CHANGE {
            self.errors = self.errors.wrapping_add(1);
        }
        match (state_of(psr), self.bus_off_since_us) {
            (BusState::BusOff, None) => {
                self.bus_off_since_us = Some(now_us);
                BusEvent::BusOff
            }
            (BusState::BusOff, Some(_)) | (_, None) => BusEvent::None,
            (_, Some(_)) => {
                self.bus_off_since_us = None;
                BusEvent::Recovered
            }
        }
    }

    /// Bus errors counted so far (wraps after 2³²).
    pub fn errors(&self) -> u32 {
        self.errors
    }

    /// How long the controller has been bus-off [µs] (0 when it is not).
    pub fn bus_off_for_us(&self, now_us: u64) -> u64 {
        self.bus_off_since_us
            .map_or(0, |t| now_us.saturating_sub(t))
    }
}

/// The error state a PSR value shows.
pub fn state_of(psr: u32) -> BusState {
    if psr & PSR_BO != 0 {
        BusState::BusOff
    } else if psr & PSR_EP != 0 {
        BusState::Passive
    } else {
        BusState::Active
    }
}

/// Frames the main loop takes per 1 ms tick at most: 1 Mbit/s carries at
/// most ≈ 21 frames a millisecond (0-byte frames, 47 bits each), so the
/// budget keeps up with any bus and still bounds a tick's receive work.
pub const RX_PER_TICK: u16 = 32;

/// How many frames the main loop may still take before the next tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RxBudget {
    left: u16,
}

impl Default for RxBudget {
    fn default() -> Self {
        Self::new()
    }
}

impl RxBudget {
    /// A full budget.
    pub const fn new() -> Self {
        Self { left: RX_PER_TICK }
    }

    /// Whether the loop may take a frame now.
    pub fn allows(&self) -> bool {
        self.left > 0
    }

    /// A frame was taken.
    pub fn on_frame(&mut self) {
        self.left = self.left.saturating_sub(1);
    }

    /// A tick: the budget is full again.
    pub fn on_tick(&mut self) {
        self.left = RX_PER_TICK;
    }
}

/// An event source of the main loop, in the order the firmware's select
/// polls them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Event {
    /// The 1 ms tick.
    Tick,
    /// An ADC scan.
    Scan,
    /// A received frame.
    Frame,
}

/// The main loop's choice among the ready sources: the tick first, then a
/// scan, then a frame if the budget allows (what the firmware's biased
/// `select3` does; `None`: wait).
pub fn pick(tick: bool, scan: bool, frame: bool, budget: &RxBudget) -> Option<Event> {
    if tick {
        Some(Event::Tick)
    } else if scan {
        Some(Event::Scan)
    } else if frame && budget.allows() {
        Some(Event::Frame)
    } else {
        None
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "busmon_tests.rs"]
mod tests;

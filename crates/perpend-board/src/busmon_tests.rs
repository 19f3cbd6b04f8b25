//! Tests of [`BusMonitor`] against a fake PSR that resets LEC on every
//! read, and of the main loop's scheduling policy under a receive flood.

use super::*;

/// PSR as the M_CAN core: LEC is set to 7 by every read.
struct FakePsr {
    psr: u32,
    reads: u32,
}

impl FakePsr {
    /// An error on the bus (LEC = `lec`).
    fn error(&mut self, lec: u32) {
        self.psr = (self.psr & !0b111) | lec;
    }
}

impl PsrRead for FakePsr {
    fn read_psr(&mut self) -> u32 {
        let v = self.psr;
        self.psr |= LEC_NO_CHANGE;
        self.reads += 1;
        v
    }
}

const ACK_ERROR: u32 = 3;

#[test]
fn two_readers_undercount_one_read_per_tick_counts_every_error() {
    let ticks = 100u32;
    // The old firmware: the bus-off poll read PSR, then the receive side
    // read it again for LEC.
    let mut old = FakePsr { psr: 7, reads: 0 };
    let mut old_errors = 0u32;
    for _ in 0..ticks {
        old.error(ACK_ERROR);
        let _bus_off = state_of(old.read_psr()) == BusState::BusOff;
        let lec = old.read_psr() & 0b111;
        if lec != LEC_NONE && lec != LEC_NO_CHANGE {
            old_errors += 1;
        }
    }
    let mut new = FakePsr { psr: 7, reads: 0 };
    let mut m = BusMonitor::new();
    for t in 0..ticks {
        new.error(ACK_ERROR);
        assert_eq!(m.tick(&mut new, u64::from(t) * 1000), BusEvent::None);
    }
    assert_eq!(old_errors, 0, "the fake does not reset LEC on read");
    assert_eq!(m.errors(), ticks);
    assert_eq!(new.reads, ticks, "PSR read more than once per tick");
}

#[test]
fn no_change_and_no_error_are_not_counted() {
    let mut m = BusMonitor::new();
    m.on_psr(LEC_NONE, 0);
    m.on_psr(LEC_NO_CHANGE, 1);
    assert_eq!(m.errors(), 0);
    m.on_psr(ACK_ERROR | PSR_EP, 2);
    assert_eq!(m.errors(), 1);
}

#[test]
fn bus_off_is_followed_from_the_same_read() {
    let mut p = FakePsr { psr: 7, reads: 0 };
    let mut m = BusMonitor::new();
    p.psr = PSR_BO | ACK_ERROR;
    assert_eq!(m.tick(&mut p, 1_000), BusEvent::BusOff);
    assert_eq!(m.errors(), 1);
    assert_eq!(m.tick(&mut p, 2_000), BusEvent::None);
    assert_eq!(m.bus_off_for_us(1_501_000), 1_500_000);
    p.psr = LEC_NO_CHANGE;
    assert_eq!(m.tick(&mut p, 3_000), BusEvent::Recovered);
    assert_eq!(m.bus_off_for_us(4_000), 0);
    assert_eq!(m.errors(), 1);
}

/// Simulates 100 ms of a loop whose frame source is always ready, each
/// frame costing 60 µs and a tick 20 µs; returns (ticks serviced, worst
/// tick lateness [µs], most frames between two ticks).
fn flood(choose: impl Fn(bool, bool, bool, &RxBudget) -> Option<Event>) -> (u32, u64, u32) {
    let (mut now, mut next_tick) = (0u64, 1_000u64);
    let (mut ticks, mut late, mut frames, mut most) = (0u32, 0u64, 0u32, 0u32);
    let mut budget = RxBudget::new();
    while now < 100_000 {
        match choose(now >= next_tick, false, true, &budget) {
            Some(Event::Tick) => {
                late = late.max(now - next_tick);
                next_tick += 1_000;
                ticks += 1;
                most = most.max(frames);
                frames = 0;
                budget.on_tick();
                now += 20;
            }
            Some(Event::Frame) => {
                budget.on_frame();
                frames += 1;
                now += 60;
            }
            Some(Event::Scan) => now += 100,
            None => now = next_tick,
        }
    }
    (ticks, late, most)
}

#[test]
fn ticks_are_serviced_under_a_receive_flood() {
    // The old order: scan, frame, tick, no budget.
    let old = |t: bool, s: bool, f: bool, _: &RxBudget| {
        [(s, Event::Scan), (f, Event::Frame), (t, Event::Tick)]
            .into_iter()
            .find(|(r, _)| *r)
            .map(|(_, e)| e)
    };
    let (old_ticks, _, _) = flood(old);
    assert_eq!(old_ticks, 0, "the flood did not starve the old order");
    let (ticks, late, most) = flood(pick);
    assert_eq!(ticks, 99);
    assert!(late <= 60, "a tick waited {late} µs (more than one frame)");
    assert!(most <= u32::from(RX_PER_TICK), "{most} frames in one tick");
}

#[test]
fn an_exhausted_budget_waits_for_the_tick_and_scans_still_run() {
    let mut b = RxBudget::new();
    for _ in 0..RX_PER_TICK {
        assert_eq!(pick(false, false, true, &b), Some(Event::Frame));
        b.on_frame();
    }
    assert_eq!(pick(false, false, true, &b), None);
    assert_eq!(pick(false, true, true, &b), Some(Event::Scan));
    assert_eq!(pick(true, true, true, &b), Some(Event::Tick));
    b.on_tick();
    assert!(b.allows());
}

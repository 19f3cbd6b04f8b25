//! Tests of [`TxQueue`] against in-repo fake controllers: one that never
//! gets an acknowledge, one that transmits slowly, one that displaces.

use super::*;

const N: usize = 8;

/// A frame with identifier `id` carrying sequence number `seq`.
fn fr(id: u16, seq: u32) -> Frame {
    Frame::new(id, &seq.to_le_bytes())
}

fn seq(f: &Frame) -> u32 {
    u32::from_le_bytes([f.data[0], f.data[1], f.data[2], f.data[3]])
}

/// Three transmit slots that never empty: a node alone on the bus.
#[derive(Default)]
struct NoAck {
    slots: std::vec::Vec<Frame>,
}

impl TxController for NoAck {
    fn try_write(&mut self, f: &Frame) -> TryWrite {
        if self.slots.len() < 3 {
            self.slots.push(*f);
            TryWrite::Accepted
        } else {
            TryWrite::Full
        }
    }
}

/// The FDCAN in queue mode as the firmware drives it: three slots, the
/// lowest identifier is sent first, a frame is held back while one with its
/// identifier is pending, and (if `displace`) a full controller gives back
/// its lowest-priority pending frame for a higher-priority one.
#[derive(Default)]
struct Bus {
    slots: [Option<Frame>; 3],
    displace: bool,
    sent: std::vec::Vec<Frame>,
}

impl Bus {
    /// One frame time: the pending frame with the lowest identifier wins.
    fn tick(&mut self) {
        let best = (0..3)
            .filter(|&i| self.slots[i].is_some())
            .min_by_key(|&i| self.slots[i].map(|f| f.id));
        if let Some(i) = best {
            self.sent.extend(self.slots[i].take());
        }
    }
}

impl TxController for Bus {
    fn try_write(&mut self, f: &Frame) -> TryWrite {
        if self.slots.iter().flatten().any(|p| p.id == f.id) {
            return TryWrite::Full;
        }
        if let Some(s) = self.slots.iter_mut().find(|s| s.is_none()) {
            *s = Some(*f);
            return TryWrite::Accepted;
        }
        if !self.displace {
            return TryWrite::Full;
        }
        let worst = (0..3).max_by_key(|&i| self.slots[i].map_or(0, |p| p.id));
        match worst.and_then(|i| self.slots[i].map(|p| (i, p))) {
            Some((i, p)) if p.id > f.id => {
                self.slots[i] = Some(*f);
                TryWrite::Displaced(p)
            }
            _ => TryWrite::Full,
        }
    }
}

/// Checks that every identifier's frames were sent in push order.
fn assert_fifo_per_id(sent: &[Frame]) {
    let mut last: std::collections::HashMap<u16, u32> = Default::default();
    for f in sent {
        if let Some(prev) = last.insert(f.id, seq(f)) {
            assert!(seq(f) > prev, "id {:#x}: {} after {prev}", f.id, seq(f));
        }
    }
}

#[test]
fn priority_order_and_fifo_among_equal_ids() {
    let mut q = TxQueue::<N>::new();
    for (id, s) in [(0x290, 1), (0x90, 2), (0x290, 3), (0x710, 4), (0x90, 5)] {
        assert!(q.push(fr(id, s)));
    }
    let order: std::vec::Vec<_> = q.frames().iter().map(|f| (f.id, seq(f))).collect();
    assert_eq!(
        order,
        [(0x90, 2), (0x90, 5), (0x290, 1), (0x290, 3), (0x710, 4)]
    );
    // A displaced frame is older than the queued ones with its id.
    q.requeue(fr(0x290, 0));
    assert_eq!((q.frames()[2].id, seq(&q.frames()[2])), (0x290, 0));
    assert_eq!(q.stats().displaced, 1);
}

#[test]
fn full_queue_drops_the_lowest_priority_and_counts() {
    let mut q = TxQueue::<4>::new();
    for (id, s) in [(5, 1), (3, 2), (7, 3), (3, 4)] {
        assert!(q.push(fr(id, s)));
    }
    assert!(!q.push(fr(9, 5)), "lowest priority: dropped itself");
    assert!(!q.push(fr(7, 6)), "equal to the last: the newer is dropped");
    assert!(q.push(fr(1, 7)), "higher priority: evicts id 7");
    let ids: std::vec::Vec<_> = q.frames().iter().map(|f| f.id).collect();
    assert_eq!(ids, [1, 3, 3, 5]);
    assert_eq!(q.stats().dropped, 3);
    assert_eq!(q.stats().peak, 4);
}

#[test]
fn no_ack_fills_the_queue_counts_overflow_and_keeps_the_highest_priority() {
    // The acquisition loop: a burst of frames per "sample", each followed
    // by a service; nothing ever waits, whatever the controller does.
    let ids = [0x190u16, 0x290, 0x390, 0x490, 0x710, 0x90];
    let mut q = TxQueue::<N>::new();
    let mut c = NoAck::default();
    let mut all = std::vec::Vec::new();
    let mut s = 0u32;
    for k in 0..10_000 {
        for &id in &ids[..1 + k % ids.len()] {
            let f = fr(id, s);
            s += 1;
            all.push(f);
            q.push(f);
        }
        q.service(&mut c);
    }
    let total = all.len() as u32;
    assert_eq!(c.slots.len(), 3);
    assert_eq!(q.len(), N);
    assert_eq!(q.stats().dropped, total - 3 - N as u32);
    // What is queued: the N highest-priority frames of those not in the
    // controller, the oldest first among equal ids.
    let mut rest: std::vec::Vec<Frame> = all.into_iter().filter(|f| !c.slots.contains(f)).collect();
    rest.sort_by_key(|f| (f.id, seq(f)));
    assert_eq!(q.frames(), &rest[..N]);
    assert!(q.frames().iter().all(|f| f.id == 0x90));
}

#[test]
fn slow_ack_delivers_everything_in_priority_and_per_id_order() {
    let mut q = TxQueue::<N>::new();
    let mut bus = Bus::default();
    let mut s = 0u32;
    let mut pushed = 0;
    // 4 TPDOs and a heartbeat every 8 frame times; an EMCY raise + reset
    // (same id) every 40.
    for t in 0..8_000 {
        if t % 8 == 0 {
            for id in [0x490u16, 0x190, 0x390, 0x290, 0x710] {
                q.push(fr(id, s));
                s += 1;
                pushed += 1;
            }
        }
        if t % 40 == 3 {
            for _ in 0..2 {
                q.push(fr(0x90, s));
                s += 1;
                pushed += 1;
            }
        }
        q.service(&mut bus);
        bus.tick();
    }
    for _ in 0..100 {
        q.service(&mut bus);
        bus.tick();
    }
    assert_eq!(q.stats().dropped, 0);
    assert_eq!(bus.sent.len(), pushed);
    assert_fifo_per_id(&bus.sent);
    assert!(q.stats().peak as usize <= N);
    // The TPDOs leave by id, not by push order; the EMCYs pushed at t = 3
    // overtake the rest of the first burst.
    let first: std::vec::Vec<u16> = bus.sent[..7].iter().map(|f| f.id).collect();
    assert_eq!(first, [0x190, 0x290, 0x390, 0x90, 0x90, 0x490, 0x710]);
}

#[test]
fn displaced_frames_are_requeued_and_sent_later() {
    let mut q = TxQueue::<N>::new();
    let mut bus = Bus {
        displace: true,
        ..Bus::default()
    };
    let mut s = 0u32;
    // Low-priority frames fill the controller, then an EMCY arrives and
    // takes a slot; the bus runs afterwards.
    for id in [0x710u16, 0x590, 0x490, 0x390] {
        q.push(fr(id, s));
        s += 1;
    }
    q.service(&mut bus);
    q.push(fr(0x90, s));
    q.service(&mut bus);
    assert!(bus.slots.iter().flatten().any(|f| f.id == 0x90));
    assert_eq!(q.stats().displaced, 1);
    assert_eq!(q.frames()[0].id, 0x590, "the displaced frame is queued");
    for _ in 0..10 {
        bus.tick();
        q.service(&mut bus);
    }
    assert!(q.is_empty());
    assert_eq!(q.stats().dropped, 0);
    let ids: std::vec::Vec<u16> = bus.sent.iter().map(|f| f.id).collect();
    assert_eq!(ids[0], 0x90);
    let mut sorted = ids.clone();
    sorted.sort_unstable();
    assert_eq!(sorted, [0x90, 0x390, 0x490, 0x590, 0x710]);
}

#[test]
fn displacing_controller_under_load_loses_nothing_and_keeps_order() {
    let mut q = TxQueue::<N>::new();
    let mut bus = Bus {
        displace: true,
        ..Bus::default()
    };
    let mut s = 0u32;
    let mut pushed = 0;
    for t in 0..5_000u32 {
        let ids: &[u16] = match t % 10 {
            0 => &[0x710, 0x590, 0x490],
            1 => &[0x90, 0x90, 0x190],
            7 => &[0x390, 0x290],
            _ => &[],
        };
        for &id in ids {
            q.push(fr(id, s));
            s += 1;
            pushed += 1;
        }
        q.service(&mut bus);
        // no frame time right after the low-priority burst: the EMCYs
        // find the controller full
        if t % 10 != 0 {
            bus.tick();
        }
    }
    for _ in 0..50 {
        q.service(&mut bus);
        bus.tick();
    }
    assert_eq!(q.stats().dropped, 0);
    assert!(q.stats().displaced > 0);
    assert_eq!(bus.sent.len(), pushed);
    assert_fifo_per_id(&bus.sent);
}

#[test]
fn a_controller_that_always_displaces_cannot_hold_the_caller() {
    // A faulty controller that hands every frame straight back.
    struct Bounce(usize);
    impl TxController for Bounce {
        fn try_write(&mut self, f: &Frame) -> TryWrite {
            self.0 += 1;
            TryWrite::Displaced(*f)
        }
    }
    let mut q = TxQueue::<N>::new();
    q.push(fr(0x181, 0));
    let mut c = Bounce(0);
    q.service(&mut c);
    assert_eq!(c.0, 2 * N + 8);
    assert_eq!(q.len(), 1);
}

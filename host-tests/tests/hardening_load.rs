//! Load (issue 7 item 5), in simulated time: the board application
//! (`perpend_board::app::App` with its CANopen device, exactly as the
//! firmware and the virtual board run it) on a simulated 1 Mbit/s CAN bus
//! with a master that sends SYNC at 1 kHz and an SDO client that saturates
//! the bus, plus an optional filler node. Deterministic: every figure below
//! is an exact count.
//!
//! Bus model: classic frames, 11-bit ids, worst-case bit stuffing:
//! `47 + 8·n` bits (3-bit intermission included) `+ ⌊(34 + 8·n − 1)/4⌋`
//! stuff bits, i.e. 135 µs for 8 data bytes and 55 µs for a SYNC
//! (7,400 frames/s of 8 bytes). At each frame boundary the pending frame
//! with the lowest id wins arbitration. Board model (the firmware's main
//! loop, `src/main.rs`): received frames go to a 3-frame RX FIFO (FDCAN
//! FIFO 0) and are handled at once unless the loop is blocked; replies go
//! through a 32-frame software queue into 3 transmit buffers sent in id
//! order; one sample per ms, `poll` every ms. A 0x1010 store blocks the
//! loop for the flash time of the steps it makes: 82 µs per double word
//! programmed, 22.02 ms per page erased (STM32G4 datasheet typical values;
//! the firmware's flash driver is blocking), during which frames beyond
//! the RX FIFO are lost and samples are skipped.
#![allow(missing_docs, clippy::unwrap_used, clippy::panic)]

use std::collections::VecDeque;

use perpend_board::acq::{counts_for_signal, signal_for_mm};
use perpend_board::app::App;
use perpend_board::pipeline::Sample;
use perpend_board::storage::{host_store, HostFlash, SeqStore};
use perpend_can::od::{SAVE_SIGNATURE, UNLOCK_SIGNATURE};
use perpend_can::Frame;
use perpend_core::geometry::Plane;
use perpend_core::model::distance;
use perpend_core::params::Params;

type HostApp = App<SeqStore<HostFlash>>;

/// Factory node-id of the board.
const NODE: u16 = 0x20;
const TPDO_IDS: [u16; 4] = [0x180 + NODE, 0x280 + NODE, 0x380 + NODE, 0x480 + NODE];
/// The filler node's frames: SDO requests to another node (0x21), just
/// below ours in priority.
const FILLER: u16 = 0x600 + NODE + 1;
const RX_FIFO: usize = 3;
const SW_QUEUE: usize = 32;
const TX_BUFFERS: usize = 3;
const T_PROG_US: u64 = 82;
const T_ERASE_US: u64 = 22_020;

/// Bits of a classic data frame on the wire, worst-case stuffing, with the
/// 3-bit intermission (= µs at 1 Mbit/s).
fn frame_bits(f: &Frame) -> u64 {
    let n = if f.rtr { 0 } else { f.len as u64 };
    47 + 8 * n + (34 + 8 * n - 1) / 4
}

/// ADC counts of the factory head looking at the demo plane, with a ±1
/// count dither so that no sensor looks stuck.
fn counts(k: u64) -> [u16; 4] {
    let p = Params::factory();
    let plane = Plane::from_abcd(0.035, -0.052, 1.0, -40.0).unwrap();
    let head = p.head.cast::<f64>();
    core::array::from_fn(|i| {
        let mm = distance(&head.sensors[i], &plane, i).unwrap() as f32;
        let t = &p.transfer[i];
        let c = counts_for_signal(signal_for_mm(mm, t), t, &p.acq);
        let dither = ((k + i as u64) % 3) as i32 - 1;
        (c as i32 + dither) as u16
    })
}

/// How the SDO client behaves.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Client {
    /// One request at a time, the next one the moment the answer arrives
    /// (a conformant client at its maximum rate).
    Saturating,
    /// A new request whenever the previous frame has left, answers or not
    /// (not conformant: a flood).
    Flood,
}

/// The requests the client cycles through (all answered with one frame in
/// operational): uploads, refused writes, unknown objects, a block
/// transfer request.
const REQUESTS: [[u8; 8]; 8] = [
    [0x40, 0x18, 0x10, 1, 0, 0, 0, 0],       // identity vendor
    [0x40, 0x02, 0x20, 1, 0, 0, 0, 0],       // θ1
    [0x40, 0x05, 0x20, 0, 0, 0, 0, 0],       // status
    [0x23, 0x00, 0x23, 1, 0xD0, 7, 0, 0],    // period in operational: refused
    [0x40, 0x00, 0x30, 0, 0, 0, 0, 0],       // no such object
    [0x2B, 0x17, 0x10, 0, 0xE8, 0x03, 0, 0], // heartbeat 1000 ms (unchanged)
    [0xA0, 0x08, 0x10, 0, 0, 0, 0, 0],       // block upload: refused
    [0x40, 0x07, 0x20, 0, 0, 0, 0, 0],       // sample counter
];

#[derive(Debug, Default, Clone, Copy, PartialEq)]
struct Window {
    tpdos: [bool; 4],
    counter: Option<u32>,
}

/// What a run measured.
#[derive(Debug, Default, Clone, PartialEq)]
struct Stats {
    duration_us: u64,
    frames: u64,
    busy_us: u64,
    syncs: u64,
    missed: u64,
    missed_outside_stalls: u64,
    stale: u64,
    sdo_requests: u64,
    sdo_responses: u64,
    filler: u64,
    rx_lost: u64,
    tx_dropped: u64,
    samples_skipped: u64,
    stall_us: u64,
    stores: u32,
    store_response: Option<[u8; 8]>,
}

struct Sim {
    app: HostApp,
    now: u64,
    client: Client,
    filler: bool,
    sync_period: u64,
    /// When the client asks for the store (µs), once.
    store_at: Option<u64>,
    store_cost_us: u64,
    // master side
    master_q: Vec<Frame>,
    /// The last request sent was the store; its answer is recorded.
    awaiting_store: bool,
    next_req: usize,
    // board side
    rx: VecDeque<Frame>,
    sw: VecDeque<Frame>,
    hw: Vec<Frame>,
    stalled_until: Option<u64>,
    held: Vec<Frame>,
    // accounting
    windows: Vec<(u64, Window, bool)>,
    st: Stats,
    k_sample: u64,
}

impl Sim {
    fn new(app: HostApp, client: Client, filler: bool, sync_period: u64) -> Self {
        Self {
            app,
            now: 0,
            client,
            filler,
            sync_period,
            store_at: None,
            store_cost_us: 0,
            master_q: Vec::new(),
            awaiting_store: false,
            next_req: 0,
            rx: VecDeque::new(),
            sw: VecDeque::new(),
            hw: Vec::new(),
            stalled_until: None,
            held: Vec::new(),
            windows: Vec::new(),
            st: Stats::default(),
            k_sample: 0,
        }
    }

    fn board_out(&mut self, frames: Vec<Frame>) {
        for f in frames {
            if self.sw.len() < SW_QUEUE {
                self.sw.push_back(f);
            } else {
                self.st.tx_dropped += 1;
            }
        }
        while self.hw.len() < TX_BUFFERS {
            match self.sw.pop_front() {
                Some(f) => self.hw.push(f),
                None => break,
            }
        }
    }

    /// The board's main loop, as far as it can run now.
    fn board_run(&mut self) {
        if let Some(t) = self.stalled_until {
            if self.now < t {
                return;
            }
            self.stalled_until = None;
            let held = std::mem::take(&mut self.held);
            self.board_out(held);
        }
        while let Some(f) = self.rx.pop_front() {
            let stores = self.app.stores();
            let mut out = Vec::new();
            self.app.handle(&f, self.now, &mut |g| out.push(g));
            if self.app.stores() != stores {
                // the flash write blocks the loop; the confirmation leaves
                // when it is done
                let until = self.now + self.store_cost_us;
                self.st.stall_us += self.store_cost_us;
                self.stalled_until = Some(until);
                self.held = out;
                return;
            }
            self.board_out(out);
        }
    }

    fn master_enqueue_request(&mut self) {
        let mut req = REQUESTS[self.next_req % REQUESTS.len()];
        self.next_req += 1;
        if self.store_at.is_some_and(|t| self.now >= t) {
            self.store_at = None;
            req = [0x23, 0x10, 0x10, 1, 0, 0, 0, 0];
            req[4..].copy_from_slice(&SAVE_SIGNATURE.to_le_bytes());
            self.awaiting_store = true;
        }
        self.master_q.push(Frame::new(0x600 + NODE, &req));
    }

    fn master_receive(&mut self, f: &Frame) {
        if f.id == 0x580 + NODE {
            self.st.sdo_responses += 1;
            if std::mem::take(&mut self.awaiting_store) {
                self.st.store_response = Some(f.data);
            }
            if self.client == Client::Saturating {
                self.master_enqueue_request();
            }
        } else if let Some(k) = TPDO_IDS.iter().position(|&id| id == f.id) {
            if let Some((_, w, _)) = self.windows.last_mut() {
                w.tpdos[k] = true;
                if k == 1 {
                    w.counter = Some(u32::from_le_bytes([
                        f.data[4], f.data[5], f.data[6], f.data[7],
                    ]));
                }
            }
        }
    }

    fn run(&mut self, until: u64) -> Stats {
        let start = self.now;
        let mut next_sync = self.now + self.sync_period;
        let mut next_sample = self.now + 500;
        let mut next_poll = self.now + 250;
        // (frame, from the board, completion time)
        let mut inflight: Option<(Frame, bool, u64)> = None;
        self.master_enqueue_request();
        while self.now < until {
            if inflight.is_none() {
                if self.filler && !self.master_q.iter().any(|f| f.id == FILLER) {
                    self.master_q
                        .push(Frame::new(FILLER, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]));
                }
                let m = self
                    .master_q
                    .iter()
                    .enumerate()
                    .min_by_key(|(_, f)| f.id)
                    .map(|(i, f)| (i, f.id));
                let b = self
                    .hw
                    .iter()
                    .enumerate()
                    .min_by_key(|(_, f)| f.id)
                    .map(|(i, f)| (i, f.id));
                let pick = match (m, b) {
                    (Some((i, a)), Some((_, c))) if a < c => Some((self.master_q.remove(i), false)),
                    (Some((i, _)), None) => Some((self.master_q.remove(i), false)),
                    (_, Some((j, _))) => Some((self.hw.remove(j), true)),
                    (None, None) => None,
                };
                if let Some((f, from_board)) = pick {
                    let bits = frame_bits(&f);
                    self.st.busy_us += bits;
                    inflight = Some((f, from_board, self.now + bits));
                }
            }
            let mut t = next_sync.min(next_sample).min(next_poll).min(until);
            if let Some((_, _, done)) = inflight {
                t = t.min(done);
            }
            if let Some(s) = self.stalled_until {
                t = t.min(s.max(self.now));
            }
            self.now = t;
            if let Some((f, from_board, done)) = inflight {
                if done == self.now {
                    inflight = None;
                    self.st.frames += 1;
                    if from_board {
                        self.master_receive(&f);
                        self.board_out(Vec::new());
                    } else {
                        if f.id == 0x080 {
                            let stalled = self.stalled_until.is_some_and(|s| s > self.now);
                            self.windows.push((self.now, Window::default(), stalled));
                            self.st.syncs += 1;
                        } else if f.id == FILLER {
                            self.st.filler += 1;
                        } else if f.id == 0x600 + NODE {
                            self.st.sdo_requests += 1;
                            if self.client == Client::Flood {
                                self.master_enqueue_request();
                            }
                        }
                        if self.rx.len() < RX_FIFO {
                            self.rx.push_back(f);
                        } else {
                            self.st.rx_lost += 1;
                        }
                    }
                }
            }
            if next_sync == self.now {
                self.master_q.push(Frame::new(0x080, &[]));
                next_sync += self.sync_period;
            }
            let stalled = self.stalled_until.is_some_and(|s| s > self.now);
            if next_sample == self.now {
                if stalled {
                    self.st.samples_skipped += 1;
                } else {
                    self.k_sample += 1;
                    let s = Sample {
                        counts: counts(self.k_sample),
                        ..Sample::default()
                    };
                    self.app.on_sample(&s, self.now);
                }
                next_sample += 1000;
            }
            if next_poll == self.now {
                if !stalled {
                    let mut out = Vec::new();
                    self.app.poll(self.now, &mut |g| out.push(g));
                    self.board_out(out);
                }
                next_poll += 1000;
            }
            self.board_run();
        }
        // every SYNC window but the last (still open) is complete
        let done = self.windows.len().saturating_sub(1);
        let mut prev: Option<u32> = None;
        for (_, w, stalled) in &self.windows[..done] {
            if !w.tpdos.iter().all(|&x| x) {
                self.st.missed += 1;
                if !stalled {
                    self.st.missed_outside_stalls += 1;
                }
            }
            if let (Some(a), Some(b)) = (prev, w.counter) {
                if b == a {
                    self.st.stale += 1;
                }
            }
            prev = w.counter.or(prev);
        }
        self.st.syncs = done as u64;
        self.st.duration_us = self.now - start;
        self.st.stores = self.app.stores();
        self.st.clone()
    }
}

/// A board in operational state on a fresh flash.
fn operational_board(flash: HostFlash) -> HostApp {
    let mut app = App::new(host_store(flash));
    app.poll(0, &mut |_| {});
    app.handle(&Frame::new(0, &[0x01, NODE as u8]), 10, &mut |_| {});
    app
}

fn report(name: &str, s: &Stats) {
    let secs = s.duration_us as f64 * 1e-6;
    eprintln!(
        "{name}: {:.0} frames/s, bus {:.1} % busy, {} SYNC, {} missed ({} outside stalls), {} stale, \
         SDO {}/{} req/resp ({:.0} req/s), filler {}, rx lost {}, tx dropped {}, samples skipped {}, stall {} µs",
        s.frames as f64 / secs,
        100.0 * s.busy_us as f64 / s.duration_us as f64,
        s.syncs,
        s.missed,
        s.missed_outside_stalls,
        s.stale,
        s.sdo_requests,
        s.sdo_responses,
        s.sdo_requests as f64 / secs,
        s.filler,
        s.rx_lost,
        s.tx_dropped,
        s.samples_skipped,
        s.stall_us
    );
}

#[test]
fn frame_times_at_1_mbit() {
    assert_eq!(frame_bits(&Frame::new(0x80, &[])), 55);
    assert_eq!(frame_bits(&Frame::new(0x190, &[0; 8])), 135);
    assert_eq!(frame_bits(&Frame::new(0x710, &[0])), 65);
}

#[test]
fn sync_at_1_khz_with_a_saturating_sdo_client_misses_nothing() {
    // A conformant client at its maximum rate plus a filler node: the bus
    // is 100 % busy; every SYNC still gets its four TPDOs with a new sample.
    let mut sim = Sim::new(
        operational_board(HostFlash::new()),
        Client::Saturating,
        true,
        1000,
    );
    let s = sim.run(2_000_000);
    report("saturating client + filler, SYNC 1 kHz", &s);
    assert_eq!(s.syncs, 1998);
    assert_eq!(s.missed, 0);
    assert_eq!(s.stale, 0);
    assert_eq!((s.rx_lost, s.tx_dropped, s.samples_skipped), (0, 0, 0));
    // every request answered (the last one may still be in flight)
    assert!(s.sdo_requests - s.sdo_responses <= 1);
    assert!(s.sdo_requests > 1000, "{}", s.sdo_requests);
    // the bus is saturated: > 98 % busy, > 7,300 frames/s
    assert!(s.busy_us * 100 > 98 * s.duration_us, "{s:?}");
    assert!(s.frames > 2 * 7_300, "{s:?}");
}

#[test]
fn sync_at_1_khz_with_an_sdo_flood_misses_nothing() {
    // A client that does not wait for answers: requests back to back.
    let mut sim = Sim::new(
        operational_board(HostFlash::new()),
        Client::Flood,
        false,
        1000,
    );
    let s = sim.run(2_000_000);
    report("SDO flood, SYNC 1 kHz", &s);
    assert_eq!(s.syncs, 1998);
    assert_eq!(s.missed, 0);
    assert_eq!(s.stale, 0);
    assert_eq!((s.rx_lost, s.tx_dropped, s.samples_skipped), (0, 0, 0));
    assert!(s.sdo_requests - s.sdo_responses <= 1);
    assert!(s.busy_us * 100 > 98 * s.duration_us, "{s:?}");
    assert!(s.frames > 2 * 7_300, "{s:?}");
    // SYNC + 4 TPDOs take 595 µs of every ms; SDO gets the rest
    assert!(s.sdo_requests > 2 * 1_300, "{}", s.sdo_requests);
}

#[test]
fn sync_rate_limit_of_the_bus() {
    // SYNC + four 8-byte TPDOs = 595 µs: up to 1.68 kHz fits the bus even
    // under the flood; at 2 kHz some TPDOs cannot fit and SYNCs go
    // unanswered (a bus limit, not the board's).
    for (period, fits) in [(650u64, true), (500, false)] {
        let mut sim = Sim::new(
            operational_board(HostFlash::new()),
            Client::Flood,
            false,
            period,
        );
        let s = sim.run(1_000_000);
        report(&format!("SDO flood, SYNC every {period} µs"), &s);
        assert_eq!(s.rx_lost, 0);
        if fits {
            assert_eq!((s.missed, s.tx_dropped), (0, 0));
        } else {
            // the TPDOs pile up in the board's queue and are dropped
            assert!(s.missed > 0 && s.tx_dropped > 0);
        }
    }
}

/// Flash steps and erases of the store the scenario makes, measured on a
/// probe board over a copy of the same flash: `(steps, erases)`.
fn store_cost(flash: &HostFlash, writes: &[[u8; 8]]) -> (u32, u32) {
    let mut app = App::new(host_store(flash.clone()));
    app.poll(0, &mut |_| {});
    for w in writes {
        app.handle(&Frame::new(0x600 + NODE, w), 10, &mut |_| {});
    }
    let mut save = [0x23, 0x10, 0x10, 1, 0, 0, 0, 0];
    save[4..].copy_from_slice(&SAVE_SIGNATURE.to_le_bytes());
    app.handle(&Frame::new(0x600 + NODE, &save), 20, &mut |_| {});
    assert_eq!(app.stores(), 1);
    let f = app.into_store().into_flash();
    (f.steps() - flash.steps(), f.erases() - flash.erases())
}

fn sdo_write(index: u16, sub: u8, data: &[u8]) -> [u8; 8] {
    let n = data.len();
    let i = index.to_le_bytes();
    let mut req = [0x23 | (((4 - n) as u8) << 2), i[0], i[1], sub, 0, 0, 0, 0];
    req[4..4 + n].copy_from_slice(data);
    req
}

fn upload_u32(app: &mut HostApp, t: u64, index: u16, sub: u8) -> u32 {
    let i = index.to_le_bytes();
    let mut out = Vec::new();
    app.handle(
        &Frame::new(0x600 + NODE, &[0x40, i[0], i[1], sub, 0, 0, 0, 0]),
        t,
        &mut |f| out.push(f),
    );
    let r = out.iter().find(|f| f.id == 0x580 + NODE).unwrap();
    assert_eq!(r.data[0] & 0xE3, 0x43, "{:02x?}", r.data);
    u32::from_le_bytes([r.data[4], r.data[5], r.data[6], r.data[7]])
}

#[test]
fn store_during_the_flood_is_neither_lost_nor_corrupted() {
    // The calibration and configuration to store.
    let values: [(u16, u8, u32); 5] = [
        (0x2101, 1, 50.125f32.to_bits()),
        (0x2102, 8, 0.003f32.to_bits()),
        (0x2203, 4, 81.5f32.to_bits()),
        (0x2104, 14, 23.5f32.to_bits()),
        (0x2300, 4, 0.06f32.to_bits()),
    ];
    let mut writes = vec![sdo_write(0x2010, 0, &UNLOCK_SIGNATURE.to_le_bytes())];
    for (i, s, v) in values {
        writes.push(sdo_write(i, s, &v.to_le_bytes()));
    }
    // Two flash states: fresh (the store only programs) and after as many
    // earlier stores as it takes for this store to erase a page first.
    let mut save = [0x23, 0x10, 0x10, 1, 0, 0, 0, 0];
    save[4..].copy_from_slice(&SAVE_SIGNATURE.to_le_bytes());
    let mut full = HostFlash::new();
    let mut earlier = 0;
    while store_cost(&full, &writes).1 == 0 {
        let mut app = App::new(host_store(full));
        app.poll(0, &mut |_| {});
        app.handle(&Frame::new(0x600 + NODE, &save), 10, &mut |_| {});
        assert_eq!(app.stores(), 1);
        full = app.into_store().into_flash();
        earlier += 1;
        assert!(earlier < 20);
    }
    for (name, flash) in [
        ("fresh flash", HostFlash::new()),
        ("flash needing an erase", full),
    ] {
        let (steps, erases) = store_cost(&flash, &writes);
        let cost = u64::from(steps - erases) * T_PROG_US + u64::from(erases) * T_ERASE_US;
        let mut app = App::new(host_store(flash));
        app.poll(0, &mut |_| {});
        for w in &writes {
            let mut out = Vec::new();
            app.handle(&Frame::new(0x600 + NODE, w), 10, &mut |f| out.push(f));
            assert_eq!(out[0].data[0], 0x60);
        }
        app.handle(&Frame::new(0, &[0x01, NODE as u8]), 20, &mut |_| {});
        let mut sim = Sim::new(app, Client::Saturating, true, 1000);
        sim.store_cost_us = cost;
        sim.store_at = Some(700_000);
        let s = sim.run(1_500_000);
        report(
            &format!("store during the flood ({name}: {steps} flash steps, {erases} erases)"),
            &s,
        );
        // the store was made and confirmed
        assert_eq!(s.stores, 1);
        assert_eq!(s.store_response.map(|r| r[0]), Some(0x60));
        assert_eq!(s.stall_us, cost);
        // misses only while the loop was blocked by the flash
        assert_eq!(s.missed_outside_stalls, 0, "{s:?}");
        assert!(s.missed <= cost / 1000 + 1, "{s:?}");
        assert_eq!(s.tx_dropped, 0);
        // after the flood: pre-operational, reset node, read back
        let mut app = sim.app;
        let t = sim.now + 1000;
        app.handle(&Frame::new(0, &[0x80, NODE as u8]), t, &mut |_| {});
        app.handle(&Frame::new(0, &[0x81, NODE as u8]), t + 100, &mut |_| {});
        app.poll(t + 200, &mut |_| {});
        for (i, sub, v) in values {
            assert_eq!(
                upload_u32(&mut app, t + 300, i, sub),
                v,
                "{i:#06x}/{sub} after reset node"
            );
        }
        // and after a power cycle, from the flash
        let mut f = app.into_store().into_flash();
        f.power_on();
        let mut app = App::new(host_store(f));
        assert_eq!(app.boot(), perpend_board::storage::Boot::Stored);
        app.poll(0, &mut |_| {});
        for (i, sub, v) in values {
            assert_eq!(
                upload_u32(&mut app, 100, i, sub),
                v,
                "{i:#06x}/{sub} after power cycle"
            );
        }
    }
}

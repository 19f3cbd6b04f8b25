//! Tests of the LSS slave (CiA 305): one per service, on a simulated bus
//! of several devices (identical frames sent at the same time merge into
//! one, as on CAN), and a fastscan master that bisects the 128-bit
//! identities.

use super::*;
use crate::{Defaults, Device, Frame, NmtState, Request};
use proptest::prelude::*;

/// Several devices on one bus, a master, a clock.
struct Net {
    devs: Vec<Device>,
    now: u64,
}

fn defaults(serial: u32) -> Defaults {
    Defaults::nominal().with_serial(serial)
}

impl Net {
    /// Devices with node-ids `ids` (0xFF: non-configured) and serials
    /// `serials`, started (first poll done).
    fn new(ids: &[u8], serials: &[u32]) -> Self {
        let devs = ids
            .iter()
            .zip(serials)
            .map(|(&id, &s)| Device::new(id, &defaults(s)))
            .collect();
        let mut n = Net { devs, now: 0 };
        n.poll();
        n
    }

    fn poll(&mut self) -> Vec<Frame> {
        let mut out = Vec::new();
        for d in &mut self.devs {
            d.poll(self.now, &mut |f| out.push(f));
        }
        out
    }

    fn advance_ms(&mut self, ms: u64) -> Vec<Frame> {
        let mut out = Vec::new();
        for _ in 0..ms {
            self.now += 1000;
            out.extend(self.poll());
        }
        out
    }

    /// Sends `f`; returns what the devices answered, identical frames
    /// merged.
    fn send(&mut self, f: Frame) -> Vec<Frame> {
        let mut out: Vec<Frame> = Vec::new();
        for d in &mut self.devs {
            d.handle(&f, self.now, &mut |g| {
                if !out.contains(&g) {
                    out.push(g)
                }
            });
        }
        out
    }

    /// Sends LSS request `d` and returns the LSS answers' payloads.
    fn lss(&mut self, d: [u8; 8]) -> Vec<[u8; 8]> {
        self.send(Frame::new(MASTER_ID, &d))
            .into_iter()
            .filter(|f| f.id == SLAVE_ID && f.len == 8)
            .map(|f| f.data)
            .collect()
    }

    fn lss_word(&mut self, c: u8, w: u32) -> Vec<[u8; 8]> {
        let b = w.to_le_bytes();
        self.lss([c, b[0], b[1], b[2], b[3], 0, 0, 0])
    }

    fn global(&mut self, mode: u8) -> Vec<[u8; 8]> {
        self.lss([cs::SWITCH_GLOBAL, mode, 0, 0, 0, 0, 0, 0])
    }

    /// Switch state selective with `id`; the answers.
    fn selective(&mut self, id: [u32; 4]) -> Vec<[u8; 8]> {
        let mut last = Vec::new();
        for (k, w) in id.into_iter().enumerate() {
            last = self.lss_word(cs::SELECTIVE_VENDOR + k as u8, w);
        }
        last
    }

    /// Completes pending store requests with `ok`; the LSS answers.
    fn finish_stores(&mut self, ok: bool) -> Vec<[u8; 8]> {
        let mut out = Vec::new();
        for d in &mut self.devs {
            if let Some(Request::StoreLss { .. }) = d.pending_request() {
                d.finish_request(ok, &mut |f| out.push(f.data)).unwrap();
            }
        }
        out
    }

    /// One fastscan request; whether any slave answered 0x4F.
    fn fastscan(&mut self, id: u32, bit: u8, sub: u8, next: u8) -> bool {
        let b = id.to_le_bytes();
        let a = self.lss([cs::FASTSCAN, b[0], b[1], b[2], b[3], bit, sub, next]);
        a.iter().any(|d| d[0] == cs::IDENTIFY_SLAVE)
    }

    /// The CiA 305 fastscan master: the smallest identity of the
    /// non-configured slaves, which is then in configuration state.
    fn scan(&mut self) -> Option<[u32; 4]> {
        if !self.fastscan(0, 0x80, 0, 0) {
            return None;
        }
        let mut id = [0u32; 4];
        for sub in 0..4u8 {
            for bit in (0..32u8).rev() {
                if !self.fastscan(id[sub as usize], bit, sub, sub) {
                    id[sub as usize] |= 1 << bit;
                }
            }
            let next = (sub + 1) & 3;
            if !self.fastscan(id[sub as usize], 0, sub, next) {
                return None;
            }
        }
        Some(id)
    }
}

fn identity(serial: u32) -> [u32; 4] {
    let d = defaults(serial).identity;
    [d.vendor_id, d.product_code, d.revision, d.serial]
}

const INQUIRE_NODE: [u8; 8] = [cs::INQUIRE_NODE_ID, 0, 0, 0, 0, 0, 0, 0];

#[test]
fn switch_state_global_gates_the_configuration_services() {
    let mut n = Net::new(&[0x10], &[7]);
    assert!(n.lss(INQUIRE_NODE).is_empty(), "waiting: no answer");
    assert!(n.global(1).is_empty(), "switch global has no answer");
    assert_eq!(n.devs[0].lss_state(), LssState::Configuration);
    assert_eq!(n.lss(INQUIRE_NODE), vec![reply_code(0x5E, 0x10)]);
    n.global(0);
    assert_eq!(n.devs[0].lss_state(), LssState::Waiting);
    assert!(n.lss(INQUIRE_NODE).is_empty());
    // Other lengths than 8 are ignored.
    n.send(Frame::new(MASTER_ID, &[cs::SWITCH_GLOBAL, 1]));
    assert_eq!(n.devs[0].lss_state(), LssState::Waiting);
}

#[test]
fn switch_state_selective_needs_all_four_words_in_order() {
    let mut n = Net::new(&[0x10, 0x10], &[100, 200]);
    let mut wrong = identity(200);
    wrong[2] ^= 1;
    assert!(n.selective(wrong).is_empty());
    assert!(n.devs.iter().all(|d| d.lss_state() == LssState::Waiting));
    // Out of order (serial first): nothing.
    n.lss_word(cs::SELECTIVE_SERIAL, 200);
    let id = identity(200);
    for k in 1..4u8 {
        assert!(n
            .lss_word(cs::SELECTIVE_VENDOR + k, id[k as usize])
            .is_empty());
    }
    assert!(n.devs.iter().all(|d| d.lss_state() == LssState::Waiting));
    assert_eq!(n.selective(id), vec![reply_code(cs::SELECTIVE_ANSWER, 0)]);
    assert_eq!(n.devs[0].lss_state(), LssState::Waiting);
    assert_eq!(n.devs[1].lss_state(), LssState::Configuration);
    // Only the selected one answers an inquiry.
    let s = n.lss([cs::INQUIRE_SERIAL, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(s, vec![reply_u32(cs::INQUIRE_SERIAL, 200)]);
}

#[test]
fn inquire_identity_returns_0x1018() {
    let mut n = Net::new(&[0x10], &[0xC0FF_EE01]);
    n.global(1);
    let want = identity(0xC0FF_EE01);
    for k in 0..4u8 {
        let c = cs::INQUIRE_VENDOR + k;
        let got = n.lss([c, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(got, vec![reply_u32(c, want[k as usize])]);
        assert_eq!(Some(want[k as usize]), n.devs[0].read_u32(0x1018, k + 1));
    }
}

#[test]
fn configure_node_id_is_pending_until_reset_communication() {
    let mut n = Net::new(&[0x10], &[1]);
    n.global(1);
    for bad in [0u8, 128, 0xFE] {
        let a = n.lss([cs::CONFIGURE_NODE_ID, bad, 0, 0, 0, 0, 0, 0]);
        assert_eq!(a, vec![reply_code(0x11, ERR_NOT_SUPPORTED)], "{bad}");
    }
    let a = n.lss([cs::CONFIGURE_NODE_ID, 0x23, 0, 0, 0, 0, 0, 0]);
    assert_eq!(a, vec![reply_code(0x11, ERR_NONE)]);
    assert_eq!(n.devs[0].communication().node_id, 0x23);
    assert_eq!(n.devs[0].node_id(), 0x10, "pending, not active");
    assert_eq!(n.lss(INQUIRE_NODE), vec![reply_code(0x5E, 0x10)]);
    n.global(0);
    n.send(Frame::new(0, &[0x82, 0x10]));
    let out = n.poll();
    assert_eq!(out, vec![Frame::new(0x723, &[0])], "boot-up as 0x23");
    assert_eq!(n.devs[0].node_id(), 0x23);
}

#[test]
fn configure_bit_timing_accepts_what_the_board_can_run() {
    let mut n = Net::new(&[0x10], &[1]);
    n.global(1);
    for index in 0..12u8 {
        let a = n.lss([cs::CONFIGURE_BIT_TIMING, 0, index, 0, 0, 0, 0, 0]);
        let ok = matches!(index, 0 | 2 | 3 | 4);
        let code = if ok { ERR_NONE } else { ERR_NOT_SUPPORTED };
        assert_eq!(a, vec![reply_code(0x13, code)], "index {index}");
    }
    let a = n.lss([cs::CONFIGURE_BIT_TIMING, 1, 2, 0, 0, 0, 0, 0]);
    assert_eq!(a, vec![reply_code(0x13, ERR_NOT_SUPPORTED)], "table 1");
    assert_eq!(supported(0, 2), Some(500));
    assert_eq!(supported(0, 4), Some(125));
    assert_eq!(supported(0, 1), None, "800 kbit/s: no board timing");
}

#[test]
fn activate_bit_timing_switches_after_the_delay_and_stays_silent_twice_it() {
    let mut n = Net::new(&[0x10], &[1]);
    n.poll();
    n.global(1);
    n.lss([cs::CONFIGURE_BIT_TIMING, 0, 2, 0, 0, 0, 0, 0]);
    assert_eq!(
        n.devs[0].communication().bit_rate_kbps,
        1000,
        "configured only"
    );
    let t0 = n.now;
    n.lss([cs::ACTIVATE_BIT_TIMING, 100, 0, 0, 0, 0, 0, 0]); // 100 ms
    let heard = n.advance_ms(99);
    assert!(heard.is_empty(), "silent before the switch: {heard:?}");
    assert!(n.lss(INQUIRE_NODE).is_empty(), "requests ignored meanwhile");
    assert_eq!(n.devs[0].take_bit_rate_switch(), None);
    n.advance_ms(1);
    assert_eq!(n.now - t0, 100_000);
    assert_eq!(n.devs[0].take_bit_rate_switch(), Some(500));
    assert_eq!(n.devs[0].take_bit_rate_switch(), None, "once");
    assert_eq!(n.devs[0].communication().bit_rate_kbps, 500);
    let heard = n.advance_ms(99);
    assert!(heard.is_empty(), "silent after the switch: {heard:?}");
    assert_eq!(n.lss(INQUIRE_NODE), Vec::<[u8; 8]>::new());
    // Heartbeat (1000 ms) resumes after the second delay.
    let heard = n.advance_ms(1000);
    assert!(heard.iter().any(|f| f.id == 0x710), "{heard:?}");
    assert_eq!(n.lss(INQUIRE_NODE), vec![reply_code(0x5E, 0x10)]);
}

#[test]
fn store_configuration_stores_0x2400_only_and_answers_the_outcome() {
    let mut n = Net::new(&[0x10], &[1]);
    n.global(1);
    n.lss([cs::CONFIGURE_NODE_ID, 0x31, 0, 0, 0, 0, 0, 0]);
    n.lss([cs::CONFIGURE_BIT_TIMING, 0, 3, 0, 0, 0, 0, 0]);
    assert!(
        n.lss([cs::STORE, 0, 0, 0, 0, 0, 0, 0]).is_empty(),
        "deferred"
    );
    let req = n.devs[0].pending_request();
    assert_eq!(req, Some(Request::StoreLss { bit_rate_kbps: 250 }));
    assert_eq!(n.finish_stores(false), vec![reply_code(0x17, ERR_STORAGE)]);
    n.lss([cs::STORE, 0, 0, 0, 0, 0, 0, 0]);
    let mut img = [0u8; crate::IMAGE_LEN];
    n.devs[0].persistent_image(&mut img);
    assert_eq!(n.finish_stores(true), vec![reply_code(0x17, ERR_NONE)]);
    // A device booting from that image starts as 0x31 at 250 kbit/s; the
    // rest is the factory state.
    let mut d = Device::new(0x20, &defaults(1));
    d.load_image(&img).unwrap();
    assert_eq!(d.node_id(), 0x31);
    assert_eq!(d.communication().bit_rate_kbps, 250);
    assert_eq!(d.read_u32(0x1017, 0), n.devs[0].read_u32(0x1017, 0));
    // An SDO store pending at the same time: storage error at once.
    n.devs[0].finish_request(true, &mut |_| {}).unwrap_err();
}

#[test]
fn unconfigured_node_waits_for_lss_then_boots_with_its_node_id() {
    let mut n = Net::new(&[UNCONFIGURED], &[5]);
    assert!(n.devs[0].lss_unconfigured());
    assert_eq!(n.devs[0].nmt_state(), NmtState::Initialising);
    let heard = n.advance_ms(3000);
    assert!(heard.is_empty(), "no boot-up, no heartbeat: {heard:?}");
    // No SDO either (at any node-id it could have).
    assert!(n
        .send(Frame::new(0x601, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]))
        .is_empty());
    assert!(n
        .send(Frame::new(0x620, &[0x40, 0, 0x10, 0, 0, 0, 0, 0]))
        .is_empty());
    n.global(1);
    assert_eq!(n.lss(INQUIRE_NODE), vec![reply_code(0x5E, UNCONFIGURED)]);
    n.lss([cs::CONFIGURE_NODE_ID, 0x12, 0, 0, 0, 0, 0, 0]);
    assert!(n.poll().is_empty(), "still waiting in configuration state");
    n.global(0);
    assert_eq!(n.poll(), vec![Frame::new(0x712, &[0])]);
    assert_eq!(n.devs[0].nmt_state(), NmtState::PreOperational);
    let a = n.send(Frame::new(0x612, &[0x40, 0x18, 0x10, 4, 0, 0, 0, 0]));
    assert_eq!(a[0].data[4..8], 5u32.to_le_bytes());
}

#[test]
fn unconfigured_node_takes_a_pending_node_id_at_nmt_reset_to_all() {
    let mut n = Net::new(&[UNCONFIGURED], &[5]);
    n.global(1);
    n.lss([cs::CONFIGURE_NODE_ID, 0x44, 0, 0, 0, 0, 0, 0]);
    n.send(Frame::new(0, &[0x82, 0x44])); // addressed: not for it yet
    assert!(n.poll().is_empty());
    n.send(Frame::new(0, &[0x82, 0]));
    assert_eq!(n.poll(), vec![Frame::new(0x744, &[0])]);
}

#[test]
fn configuring_0xff_makes_a_node_unconfigured_at_reset() {
    let mut n = Net::new(&[0x20, 0x20], &[1, 2]);
    n.global(1);
    assert_eq!(n.lss(INQUIRE_NODE), vec![reply_code(0x5E, 0x20)], "merged");
    n.lss([cs::CONFIGURE_NODE_ID, UNCONFIGURED, 0, 0, 0, 0, 0, 0]);
    n.global(0);
    assert!(n.poll().is_empty() || n.devs.iter().all(|d| !d.lss_unconfigured()));
    n.send(Frame::new(0, &[0x82, 0]));
    assert!(n.poll().is_empty(), "no boot-up");
    assert!(n.devs.iter().all(Device::lss_unconfigured));
    let a = n.lss([cs::IDENTIFY_NON_CONFIGURED, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(a, vec![reply_code(cs::NON_CONFIGURED_SLAVE, 0)]);
}

#[test]
fn identify_remote_slave_answers_inside_the_ranges() {
    let mut n = Net::new(&[0x10, 0x11, 0x12], &[10, 20, 30]);
    let id = identity(0);
    let ask = |n: &mut Net, rev: (u32, u32), ser: (u32, u32)| {
        let words = [id[0], id[1], rev.0, rev.1, ser.0, ser.1];
        let mut a = Vec::new();
        for (k, w) in words.into_iter().enumerate() {
            a = n.lss_word(cs::IDENTIFY_VENDOR + k as u8, w);
        }
        a
    };
    let yes = vec![reply_code(cs::IDENTIFY_SLAVE, 0)];
    assert_eq!(ask(&mut n, (0, u32::MAX), (15, 25)), yes);
    assert_eq!(ask(&mut n, (0, u32::MAX), (10, 10)), yes);
    assert!(ask(&mut n, (0, u32::MAX), (11, 19)).is_empty());
    assert!(ask(&mut n, (id[2] + 1, u32::MAX), (0, 100)).is_empty());
    // Not configured: none of them.
    assert!(n
        .lss([cs::IDENTIFY_NON_CONFIGURED, 0, 0, 0, 0, 0, 0, 0])
        .is_empty());
}

#[test]
fn fastscan_finds_every_unconfigured_slave_in_identity_order() {
    let serials = [0x8000_0001u32, 0x0000_0002, 0x7FFF_FFFF, 0x8000_0000];
    let mut n = Net::new(
        &[0xFF, 0xFF, 0xFF, 0xFF, 0x30],
        &[serials[0], serials[1], serials[2], serials[3], 0x0000_0001],
    );
    let mut sorted = serials;
    sorted.sort_unstable();
    for (k, want) in sorted.into_iter().enumerate() {
        let found = n.scan().expect("a slave");
        assert_eq!(found, identity(want));
        // The one found is in configuration state: give it a node-id.
        let a = n.lss([cs::CONFIGURE_NODE_ID, 0x10 + k as u8, 0, 0, 0, 0, 0, 0]);
        assert_eq!(a, vec![reply_code(0x11, 0)]);
        n.global(0);
        let boot = n.poll();
        assert_eq!(boot, vec![Frame::new(0x710 + k as u16, &[0])]);
    }
    assert_eq!(n.scan(), None, "all configured (0x30 never answered)");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    /// Whatever the identities, the master finds the smallest one and
    /// selects only it.
    #[test]
    fn fastscan_finds_the_smallest_identity(serials in proptest::collection::hash_set(any::<u32>(), 1..5)) {
        let serials: Vec<u32> = serials.into_iter().collect();
        let ids = vec![UNCONFIGURED; serials.len()];
        let mut n = Net::new(&ids, &serials);
        let found = n.scan();
        let min = *serials.iter().min().unwrap();
        prop_assert_eq!(found, Some(identity(min)));
        let selected: Vec<u32> = n.devs.iter()
            .filter(|d| d.lss_state() == LssState::Configuration)
            .map(|d| d.read_u32(0x1018, 4).unwrap())
            .collect();
        prop_assert_eq!(selected, vec![min]);
    }
}

/// An arbitrary frame, biased towards LSS and NMT.
fn any_frame() -> impl Strategy<Value = Frame> {
    let id = prop_oneof![Just(MASTER_ID), Just(0u16), 0u16..0x800];
    (id, proptest::collection::vec(any::<u8>(), 0..=8)).prop_map(|(id, d)| Frame::new(id, &d))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]
    /// Whatever it receives (LSS, NMT, anything), a non-configured node
    /// sends nothing but 8-byte LSS answers until it has a node-id, and
    /// once it sends anything else it is no longer non-configured.
    #[test]
    fn a_non_configured_node_only_answers_lss(frames in proptest::collection::vec(any_frame(), 0..200)) {
        let mut n = Net::new(&[UNCONFIGURED], &[3]);
        for f in frames {
            let was = n.devs[0].lss_unconfigured();
            let mut out = n.send(f);
            n.now += 997;
            out.extend(n.poll());
            if was && n.devs[0].lss_unconfigured() {
                for g in &out {
                    prop_assert!(g.id == SLAVE_ID && g.len == 8, "{:?}", g);
                }
            }
        }
    }
}

//! The LSS master against the in-memory bus: a cell of the board's own LSS
//! slaves (`perpend_can::lss::LssSlave`) as the peer (frame encodings,
//! selective switch, fastscan of every non-configured slave, assignment),
//! and scripted slaves for the refusals and silence.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use perpend_can::lss::{cs, Context, LssSlave, LssState, Outcome, MASTER_ID, SLAVE_ID};
use perpend_can::Frame;

use super::{refusal_words, table0_index, Identity, LssError};
use crate::bus::fake::{FakeBus, FnPeer, Peer};
use crate::canopen::Client;

const VENDOR: u32 = 0xAFFF_5050;
const PRODUCT: u32 = 0x5045_5250;
const REVISION: u32 = 0x0001_0000;

/// Slaves on one bus; every request the master sent is recorded.
struct Cell {
    slaves: Vec<(LssSlave, Context)>,
    sent: Arc<Mutex<Vec<[u8; 8]>>>,
}

impl Peer for Cell {
    fn frame(&mut self, f: &Frame, out: &mut Vec<Frame>) {
        assert_eq!(f.id, MASTER_ID);
        assert_eq!(f.len, 8);
        self.sent.lock().unwrap().push(f.data);
        for (s, ctx) in &mut self.slaves {
            let reply = match s.handle(f.payload(), ctx) {
                Some(Outcome::Reply(d)) => d,
                Some(Outcome::NodeId(id)) => {
                    ctx.pending_node_id = id;
                    [cs::CONFIGURE_NODE_ID, 0, 0, 0, 0, 0, 0, 0]
                }
                Some(Outcome::Store { .. }) => LssSlave::store_done(true),
                Some(Outcome::Waiting) => {
                    // A non-configured slave given a node-id starts with it.
                    if ctx.pending_node_id != 0xFF {
                        ctx.active_node_id = ctx.pending_node_id;
                    }
                    continue;
                }
                _ => continue,
            };
            out.push(Frame::new(SLAVE_ID, &reply));
        }
    }
}

fn ident(serial: u32) -> Identity {
    Identity {
        vendor: VENDOR,
        product: PRODUCT,
        revision: REVISION,
        serial,
    }
}

/// A client on a cell of slaves with these identities and node-ids.
fn cell(slaves: &[(Identity, u8)]) -> (Client, Arc<Mutex<Vec<[u8; 8]>>>) {
    let (peer, sent) = cell_peer(slaves);
    (client(peer), sent)
}

fn client(peer: impl Peer + 'static) -> Client {
    let mut c = Client::new(Box::new(FakeBus::new(peer)));
    c.lss_timeout = Duration::from_millis(3);
    c
}

/// The cell of slaves.
fn cell_peer(slaves: &[(Identity, u8)]) -> (Cell, Arc<Mutex<Vec<[u8; 8]>>>) {
    let sent = Arc::new(Mutex::new(Vec::new()));
    let slaves = slaves
        .iter()
        .map(|(id, node)| {
            let ctx = Context {
                identity: id.words(),
                active_node_id: *node,
                pending_node_id: *node,
                bit_rate_kbps: 1000,
            };
            (LssSlave::new(), ctx)
        })
        .collect();
    let peer = Cell {
        slaves,
        sent: sent.clone(),
    };
    (peer, sent)
}

/// A cell whose answers to the `at`-th fastscan request come only with
/// the answers to the next request (later than the window).
struct Late {
    cell: Cell,
    count: usize,
    at: usize,
    held: Vec<Frame>,
}

impl Peer for Late {
    fn frame(&mut self, f: &Frame, out: &mut Vec<Frame>) {
        let mut now = Vec::new();
        self.cell.frame(f, &mut now);
        out.append(&mut self.held);
        if f.data[0] == cs::FASTSCAN {
            self.count += 1;
            if self.count == self.at {
                self.held = now;
                return;
            }
        }
        out.extend(now);
    }
}

fn scripted(mut answer: impl FnMut(&[u8]) -> Option<[u8; 8]> + Send + 'static) -> Client {
    client(FnPeer(move |f: &Frame, out: &mut Vec<Frame>| {
        if let Some(d) = answer(f.payload()) {
            out.push(Frame::new(SLAVE_ID, &d));
        }
    }))
}

#[test]
fn requests_are_encoded_as_cia_305_says() {
    let (mut c, sent) = cell(&[(ident(0x42), 0x20)]);
    c.lss_switch_global(LssState::Configuration).unwrap();
    c.lss_configure_node_id(0x21).unwrap();
    c.lss_configure_bit_timing(500).unwrap();
    c.lss_activate_bit_timing(0x0102).unwrap();
    c.lss_store().unwrap();
    assert_eq!(
        c.lss_inquire_node_id().unwrap(),
        0x20,
        "pending until reset"
    );
    assert_eq!(c.lss_inquire_identity().unwrap(), ident(0x42));
    c.lss_switch_global(LssState::Waiting).unwrap();
    let s = sent.lock().unwrap().clone();
    assert_eq!(s[0], [0x04, 1, 0, 0, 0, 0, 0, 0]);
    assert_eq!(s[1], [0x11, 0x21, 0, 0, 0, 0, 0, 0]);
    assert_eq!(s[2], [0x13, 0, 2, 0, 0, 0, 0, 0], "table 0, index 2");
    assert_eq!(s[3], [0x15, 0x02, 0x01, 0, 0, 0, 0, 0]);
    assert_eq!(s[4], [0x17, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(s[5], [0x5E, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(
        &s[6..10].iter().map(|d| d[0]).collect::<Vec<_>>(),
        &[0x5A, 0x5B, 0x5C, 0x5D]
    );
    assert_eq!(s[10], [0x04, 0, 0, 0, 0, 0, 0, 0]);
}

#[test]
fn selective_switch_picks_one_node_by_identity() {
    let (mut c, sent) = cell(&[(ident(1), 0x20), (ident(2), 0x20), (ident(3), 0x20)]);
    c.lss_switch_selective(&ident(2)).unwrap();
    assert_eq!(c.lss_inquire_all(cs::INQUIRE_SERIAL).unwrap(), vec![2]);
    let s = sent.lock().unwrap().clone();
    assert_eq!(s[0], [0x40, 0x50, 0x50, 0xFF, 0xAF, 0, 0, 0]);
    assert_eq!(s[3], [0x43, 2, 0, 0, 0, 0, 0, 0]);
    c.lss_switch_global(LssState::Waiting).unwrap();
    let e = c.lss_switch_selective(&ident(9)).unwrap_err().to_string();
    assert!(
        e.contains("switch state selective") && e.contains("serial 0x00000009"),
        "{e}"
    );
    assert!(e.contains("fake"), "names the bus: {e}");
}

#[test]
fn global_inquiry_counts_every_node_in_configuration_state() {
    let (mut c, _) = cell(&[(ident(1), 0x20), (ident(2), 0x21)]);
    c.lss_switch_global(LssState::Configuration).unwrap();
    let mut serials = c.lss_inquire_all(cs::INQUIRE_SERIAL).unwrap();
    serials.sort_unstable();
    assert_eq!(serials, vec![1, 2]);
    c.lss_switch_global(LssState::Waiting).unwrap();
    assert!(c.lss_inquire_all(cs::INQUIRE_SERIAL).unwrap().is_empty());
    let e = c.lss_inquire_node_id().unwrap_err().to_string();
    assert!(e.contains("no node is in LSS configuration state"), "{e}");
}

#[test]
fn identify_services_count_the_answers() {
    let (mut c, _) = cell(&[(ident(5), 0xFF), (ident(6), 0x20), (ident(7), 0xFF)]);
    assert_eq!(c.lss_identify_non_configured().unwrap(), 2);
    let n = c
        .lss_identify_remote(VENDOR, PRODUCT, (0, u32::MAX), (6, 7))
        .unwrap();
    assert_eq!(n, 2);
    let n = c
        .lss_identify_remote(VENDOR, PRODUCT ^ 1, (0, u32::MAX), (0, u32::MAX))
        .unwrap();
    assert_eq!(n, 0);
}

#[test]
fn fastscan_lists_every_non_configured_node_smallest_first() {
    let serials = [0x0C0F_FEE3, 0x42, 0x8000_0001, 0x0C0F_FEE1];
    let mut nodes: Vec<(Identity, u8)> = serials.iter().map(|&s| (ident(s), 0xFF)).collect();
    nodes.push((ident(0x10), 0x20)); // configured: takes no part
    nodes.push((
        Identity {
            revision: 0x0002_0000,
            ..ident(0x7)
        },
        0xFF,
    ));
    let (mut c, _) = cell(&nodes);
    let found = c.lss_list_non_configured(Some(&ident(0)), 127).unwrap();
    let mut want: Vec<Identity> = serials.iter().map(|&s| ident(s)).collect();
    want.sort_unstable();
    want.push(Identity {
        revision: 0x0002_0000,
        ..ident(0x7)
    });
    assert_eq!(found, want, "the expected revision first, then the other");
    // Everyone is back in waiting state: a second listing finds them again.
    let again = c.lss_list_non_configured(None, 127).unwrap();
    let mut sorted = want.clone();
    sorted.sort_unstable();
    assert_eq!(again, sorted, "without expectations: plain smallest first");
    assert_eq!(c.lss_list_non_configured(None, 2).unwrap().len(), 2);
    // issue 47 point 2: the progress line hears of every node found
    let mut heard = Vec::new();
    let n = c
        .lss_list_non_configured_with(None, 127, &mut |k| heard.push(k))
        .unwrap()
        .len();
    assert_eq!(heard, (1..=n).collect::<Vec<_>>());
}

#[test]
fn fastscan_then_assign_configures_one_node_after_the_other() {
    let (mut c, _) = cell(&[(ident(3), 0xFF), (ident(1), 0xFF), (ident(2), 0x22)]);
    let mut got = Vec::new();
    while let Some(id) = c.lss_fastscan(Some(&ident(0))).unwrap() {
        assert_eq!(c.lss_inquire_node_id().unwrap(), 0xFF, "the one found");
        let node = 0x10 + got.len() as u8;
        c.lss_configure_node_id(node).unwrap();
        c.lss_store().unwrap();
        c.lss_switch_global(LssState::Waiting).unwrap();
        got.push((id.serial, node));
    }
    assert_eq!(got, vec![(1, 0x10), (3, 0x11)]);
    assert_eq!(c.lss_identify_non_configured().unwrap(), 0);
}

#[test]
fn a_late_answer_makes_a_scan_that_is_checked_and_repeated() {
    // Request 10: reset, vendor, product, revision confirmed, then serial
    // bit 31..26: bit 26 of 0x42 is 0, its answer comes late.
    let (cell, sent) = cell_peer(&[(ident(0x42), 0xFF)]);
    let late = Late {
        cell,
        count: 0,
        at: 10,
        held: Vec::new(),
    };
    let mut c = client(late);
    assert_eq!(c.lss_fastscan(Some(&ident(0))).unwrap(), Some(ident(0x42)));
    let resets = sent
        .lock()
        .unwrap()
        .iter()
        .filter(|d| d[0] == cs::FASTSCAN && d[5] == 0x80)
        .count();
    assert_eq!(resets, 2, "scanned twice");
}

#[test]
fn an_empty_bus_answers_no_fastscan() {
    let (mut c, sent) = cell(&[]);
    assert_eq!(c.lss_fastscan(None).unwrap(), None);
    assert_eq!(
        sent.lock().unwrap().as_slice(),
        &[[0x51, 0, 0, 0, 0, 0x80, 0, 0]],
        "one reset, nothing else"
    );
}

#[test]
fn refusals_are_sentences() {
    let mut c = scripted(|d| match d[0] {
        0x11 => Some([0x11, 1, 0, 0, 0, 0, 0, 0]),
        0x13 => Some([0x13, 1, 0, 0, 0, 0, 0, 0]),
        0x17 => Some([0x17, 0xFF, 0x33, 0, 0, 0, 0, 0]),
        _ => None,
    });
    let e = c.lss_configure_node_id(0).unwrap_err().to_string();
    assert!(
        e.contains("refused configure node-id: node-id out of range"),
        "{e}"
    );
    let e = c.lss_configure_bit_timing(800).unwrap_err().to_string();
    assert!(e.contains("bit timing not supported"), "{e}");
    let e = c.lss_store().unwrap_err().to_string();
    assert!(e.contains("manufacturer-specific error 0x33"), "{e}");
    let e = c.lss_configure_bit_timing(600).unwrap_err();
    assert!(matches!(e, LssError::Invalid(_)), "{e}");
    assert!(refusal_words(0x17, 2, 0).contains("storage media access error"));
    assert_eq!(table0_index(10).unwrap(), 8);
    assert_eq!(table0_index(1000).unwrap(), 0);
}

#[test]
fn silence_is_a_timeout_naming_the_bus() {
    let mut c = scripted(|_| None);
    let e = c.lss_store().unwrap_err();
    match &e {
        LssError::NoAnswer { waited, .. } => assert!(*waited >= super::STORE_TIMEOUT),
        _ => panic!("{e}"),
    }
    assert!(e.to_string().contains("on fake"), "{e}");
}

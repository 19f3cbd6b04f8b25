//! Push and pull against the board's own application on the in-memory bus
//! (no TCP, virtual time): the round trip, an interrupted push, a file for
//! another head, a board in operational.
#![allow(clippy::unwrap_used, clippy::panic)]

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use perpend_can::Frame;
use perpend_core::geometry::Plane;
use perpend_core::params::Params;
use perpend_formats::paramfile::{ParamFile, TableParams, TransferParams, TRANSFER_CURRENT};

use super::{plan, pull, push, push_with_record, read_stamp, record_hash, PushArgs};
use crate::board::node::{BoardConfig, VirtualBoard};
use crate::board::sim::SimHead;
use crate::bus::fake::{FakeBus, Peer};
use crate::canopen::Client;
use crate::node::Node;

const NODE: u8 = 0x10;

/// The virtual board, shared with the test; optionally raises `cancel`
/// after `cancel_after` calibration writes.
struct BoardPeer {
    board: Arc<Mutex<VirtualBoard>>,
    t: u64,
    cancel: Arc<AtomicBool>,
    cancel_after: Option<usize>,
    cal_writes: usize,
    /// Answer 0x2011 like a firmware without it (abort 0x06020000).
    no_stamp: bool,
    /// Answer 0x2101..0x2104 like a firmware before the spot coefficients
    /// (sub 0 = 23, sub 24/25 abort 0x06090011).
    no_spot: bool,
}

/// The answer of a firmware before the spot coefficients to an SDO
/// initiate `d` addressed to 0x2101..0x2104 (`None`: as the board).
fn pre_spot_answer(d: &[u8; 8]) -> Option<[u8; 8]> {
    if d[2] != 0x21 || !(1..=4).contains(&d[1]) {
        return None;
    }
    match d[3] {
        0 if d[0] >> 5 == 2 => Some([0x4F, d[1], d[2], 0, 23, 0, 0, 0]),
        24.. => Some([0x80, d[1], d[2], d[3], 0x11, 0x00, 0x09, 0x06]),
        _ => None,
    }
}

impl Peer for BoardPeer {
    fn frame(&mut self, f: &Frame, out: &mut Vec<Frame>) {
        let d = f.data;
        if f.id == 0x600 + NODE as u16 && d[0] >> 5 == 1 && d[2] == 0x21 {
            self.cal_writes += 1;
            if Some(self.cal_writes) == self.cancel_after {
                self.cancel.store(true, Ordering::SeqCst);
            }
        }
        self.t += 50;
        let initiate = matches!(d[0] >> 5, 1 | 2);
        if self.no_stamp && f.id == 0x600 + NODE as u16 && initiate && d[1..3] == [0x11, 0x20] {
            let abort = [0x80, d[1], d[2], d[3], 0x00, 0x00, 0x02, 0x06];
            out.push(Frame::new(0x580 + NODE as u16, &abort));
            return;
        }
        let old = (self.no_spot && f.id == 0x600 + NODE as u16 && initiate)
            .then(|| pre_spot_answer(&d))
            .flatten();
        if let Some(r) = old {
            out.push(Frame::new(0x580 + NODE as u16, &r));
            return;
        }
        self.board
            .lock()
            .unwrap()
            .handle(f, self.t, &mut |o| out.push(o));
    }
    fn idle(&mut self, out: &mut Vec<Frame>) {
        let mut b = self.board.lock().unwrap();
        self.t += b.period_us();
        b.sample(self.t);
        b.poll(self.t, &mut |o| out.push(o));
    }
}

struct Rig {
    board: Arc<Mutex<VirtualBoard>>,
    cancel: Arc<AtomicBool>,
    node: Node,
}

fn rig(cancel_after: Option<usize>) -> Rig {
    rig_with(cancel_after, false, false)
}

fn rig_with(cancel_after: Option<usize>, no_stamp: bool, no_spot: bool) -> Rig {
    let plane = Plane::from_abcd(0.02, -0.03, 1.0, -45.0).unwrap();
    let sim = SimHead::new(Params::factory().head.cast(), plane, 0.002, 3).unwrap();
    let cfg = BoardConfig {
        node_id: NODE,
        head: None,
        calibration: None,
        thermal_tau_s: 0.0,
    };
    let board = Arc::new(Mutex::new(VirtualBoard::new(&cfg, sim).unwrap()));
    let cancel = Arc::new(AtomicBool::new(false));
    let mut peer = BoardPeer {
        board: board.clone(),
        t: 0,
        cancel: cancel.clone(),
        cancel_after,
        cal_writes: 0,
        no_stamp,
        no_spot,
    };
    // Boot (the first poll sends the boot-up) and take a few samples.
    let mut early = Vec::new();
    for _ in 0..5 {
        peer.idle(&mut early);
    }
    let mut bus = FakeBus::new(peer);
    bus.inbox.extend(early);
    let mut client = Client::new(Box::new(bus));
    client.timeout = Duration::from_millis(200);
    // A heartbeat every 100 ms of virtual time (state checks stay short).
    client
        .download(NODE, 0x1017, 0, &100u16.to_le_bytes())
        .unwrap();
    Rig {
        board,
        cancel,
        node: Node::new(client, NODE),
    }
}

/// The factory head, shifted and with a gain, plus transfer functions.
fn params_file(dir: &std::path::Path, sensors: usize) -> std::path::PathBuf {
    let nominal: Vec<_> = Params::factory().head.cast::<f64>().sensors.to_vec();
    let mut truth = nominal.clone();
    for (i, s) in truth.iter_mut().enumerate() {
        s.zero.x += 0.1 * (i as f64 + 1.0);
        s.ext.gain = 0.001 * i as f64;
    }
    let mut f = ParamFile::truth(&truth[..sensors], &nominal);
    f.method = "lsq".into();
    f.thermal_tau_s = 412.75;
    for s in &mut f.sensors {
        s.transfer = Some(TransferParams {
            kind: TRANSFER_CURRENT.into(),
            scale: 150.0,
            mm_at_low: 30.0,
            mm_at_high: 70.0,
        });
    }
    let p = dir.join(format!("params{sensors}.json"));
    f.write(&p).unwrap();
    p
}

/// The thermal time constant the virtual board's pipeline applies.
fn pipeline_tau(r: &Rig) -> f32 {
    r.board
        .lock()
        .unwrap()
        .app()
        .pipeline()
        .params()
        .thermal_tau_s
}

fn args(file: std::path::PathBuf) -> PushArgs {
    PushArgs {
        file,
        preop: false,
        record: None,
    }
}

#[test]
fn push_stores_and_pull_reads_the_same_values() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut r = rig(None);
    let before = pull(&mut r.node, &r.cancel).unwrap();
    assert_eq!(before.model, "base");
    let rep = push(&mut r.node, &args(path.clone()), &r.cancel).unwrap();
    assert_eq!(rep.values, 4 * 29 + 1);
    assert!(rep.changed >= 4 * 3, "{rep:?}");
    assert!(rep
        .to_string()
        .contains("read back identical after the boot-up"));
    assert_eq!(r.board.lock().unwrap().app().stores(), 1);
    assert!(!r
        .board
        .lock()
        .unwrap()
        .app()
        .device()
        .calibration_unlocked());
    let back = pull(&mut r.node, &r.cancel).unwrap();
    let file = ParamFile::read(&path).unwrap();
    assert_eq!(back.model, "gain");
    assert_eq!(back.thermal_tau_s, file.thermal_tau_s as f32 as f64);
    assert_eq!(
        r.board.lock().unwrap().app().device().thermal_tau_s(),
        412.75
    );
    assert_eq!(pipeline_tau(&r), 412.75);
    for (a, b) in file.sensors.iter().zip(&back.sensors) {
        let f = |x: f64| x as f32 as f64;
        assert_eq!(b.zero_mm, a.zero_mm.map(f));
        assert_eq!(b.dir, a.dir.map(f));
        assert_eq!(b.ext.gain, f(a.ext.gain));
        assert_eq!(b.transfer, a.transfer);
    }
    // what pull wrote, push writes back unchanged
    let p2 = dir.path().join("back.json");
    back.write(&p2).unwrap();
    assert_eq!(
        plan(&ParamFile::read(&p2).unwrap()).unwrap(),
        plan(&back).unwrap()
    );
    let rep = push(&mut r.node, &args(p2), &r.cancel).unwrap();
    assert_eq!(rep.changed, 0);
}

#[test]
fn an_interrupted_push_stores_nothing_and_resets_to_the_stored_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut r = rig(Some(20));
    let before = pull(&mut r.node, &AtomicBool::new(false)).unwrap();
    let e = format!(
        "{:#}",
        push(&mut r.node, &args(path), &r.cancel).unwrap_err()
    );
    assert!(e.contains("nothing was stored"), "{e}");
    assert!(
        e.contains("runs its previous stored calibration again"),
        "{e}"
    );
    assert!(
        e.contains("interrupted (Ctrl-C) after 20 of 117 writes"),
        "{e}"
    );
    assert_eq!(r.board.lock().unwrap().app().stores(), 0);
    assert!(!r
        .board
        .lock()
        .unwrap()
        .app()
        .device()
        .calibration_unlocked());
    let after = pull(&mut r.node, &AtomicBool::new(false)).unwrap();
    assert_eq!(before, after);
}

#[test]
fn a_file_for_another_head_is_refused_before_any_write() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 3);
    let mut r = rig(None);
    let e = push(&mut r.node, &args(path), &r.cancel)
        .unwrap_err()
        .to_string();
    assert!(e.contains("has 3 sensors") && e.contains("has 4"), "{e}");
    assert!(e.contains("another head; nothing was written"), "{e}");
    assert_eq!(r.board.lock().unwrap().app().stores(), 0);
}

#[test]
fn out_of_range_values_are_named_before_any_write() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut f = ParamFile::read(&path).unwrap();
    f.sensors[1].ext.gain = 0.7;
    f.write(&path).unwrap();
    let e = format!("{:#}", plan(&f).unwrap_err());
    assert!(
        e.contains("sensor 2 gain = 0.7 is outside what the board accepts (-0.5 to 0.5)"),
        "{e}"
    );
}

#[test]
fn an_operational_board_is_refused_unless_preop() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut r = rig(None);
    r.node.client.nmt(NODE, crate::canopen::Nmt::Start).unwrap();
    let e = push(&mut r.node, &args(path.clone()), &r.cancel)
        .unwrap_err()
        .to_string();
    assert!(e.contains("is operational") && e.contains("--preop"), "{e}");
    assert_eq!(r.board.lock().unwrap().app().stores(), 0);
    let mut a = args(path);
    a.preop = true;
    let rep = push(&mut r.node, &a, &r.cancel).unwrap();
    assert!(rep.switched);
    assert!(rep.to_string().contains("nmt start"));
}

fn table(knots_mm: [f64; 5], values_mm: [f64; 3]) -> Option<TableParams> {
    Some(TableParams {
        knots_mm,
        values_mm,
    })
}

/// A linearity table goes to the board (sub 16..23) and comes back in
/// pull, with "linearity table" among the model's effects; a second push
/// with other knots under the active table (the board refuses knots out
/// of order while a table is active) and a push without a table (which
/// switches it off) both go through.
#[test]
fn linearity_tables_push_and_pull() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut f = ParamFile::read(&path).unwrap();
    let t1 = table([-6.0, -3.0, 0.0, 2.0, 6.0], [1e-3, -2e-3, 1.5e-3]);
    f.sensors[1].ext.linearity_table = t1;
    f.write(&path).unwrap();
    let mut r = rig(None);
    push(&mut r.node, &args(path.clone()), &r.cancel).unwrap();
    let back = pull(&mut r.node, &r.cancel).unwrap();
    assert_eq!(back.model, "gain+linearity table");
    let f32s = |t: Option<TableParams>| {
        t.map(|t| (t.knots_mm.map(|x| x as f32), t.values_mm.map(|x| x as f32)))
    };
    assert_eq!(f32s(back.sensors[1].ext.linearity_table), f32s(t1));
    assert!(back.sensors[0].ext.linearity_table.is_none());
    // Other knots: the first knot moves past the old second one, which the
    // board refuses one by one under the active table.
    let t2 = table([-2.0, 1.0, 4.0, 9.0, 20.0], [-5e-4, 1e-4, 2e-4]);
    f.sensors[1].ext.linearity_table = t2;
    f.write(&path).unwrap();
    let rep = push(&mut r.node, &args(path.clone()), &r.cancel).unwrap();
    assert_eq!(rep.changed, 8);
    let back = pull(&mut r.node, &r.cancel).unwrap();
    assert_eq!(f32s(back.sensors[1].ext.linearity_table), f32s(t2));
    // no table in the file: the board's is switched off
    f.sensors[1].ext.linearity_table = None;
    f.write(&path).unwrap();
    push(&mut r.node, &args(path), &r.cancel).unwrap();
    let back = pull(&mut r.node, &r.cancel).unwrap();
    assert_eq!(back.model, "gain");
    assert!(back.sensors.iter().all(|s| s.ext.linearity_table.is_none()));
}

/// A table whose knots are ascending in the file but coincide as REAL32
/// is refused before any write.
#[test]
fn a_table_the_board_would_refuse_is_named_before_any_write() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = ParamFile::read(&params_file(dir.path(), 4)).unwrap();
    f.sensors[2].ext.linearity_table = table([-6.0, -3.0, 0.0, 2.0, 2.0 + 1e-9], [1e-3, 0.0, 0.0]);
    let e = format!("{:#}", plan(&f).unwrap_err());
    assert!(
        e.contains("sensor 3 linearity table") && e.contains("not strictly ascending"),
        "{e}"
    );
    // the same knots without coefficients: no table, nothing to refuse
    f.sensors[2].ext.linearity_table = table([-6.0, -3.0, 0.0, 2.0, 2.0 + 1e-9], [0.0; 3]);
    assert_eq!(plan(&f).unwrap().len(), 4 * 29 + 1);
}

/// The thermal time constant: out of the board's range it is named before
/// any write; τ = 0 pushed over a lag switches the lag off, and pull
/// reads 0 back (the file then has no `thermal_tau_s`).
#[test]
fn thermal_tau_push_and_pull() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut f = ParamFile::read(&path).unwrap();
    assert_eq!(f.thermal_tau_s, 412.75);
    f.thermal_tau_s = 90_000.0;
    let e = format!("{:#}", plan(&f).unwrap_err());
    assert!(
        e.contains("thermal_tau_s (head thermal time constant) = 90000 is outside what the board accepts (0 to 86400)"),
        "{e}"
    );
    let mut r = rig(None);
    push(&mut r.node, &args(path.clone()), &r.cancel).unwrap();
    assert_eq!(pull(&mut r.node, &r.cancel).unwrap().thermal_tau_s, 412.75);
    f.thermal_tau_s = 0.0;
    f.write(&path).unwrap();
    let rep = push(&mut r.node, &args(path.clone()), &r.cancel).unwrap();
    assert_eq!(rep.changed, 1);
    let back = pull(&mut r.node, &r.cancel).unwrap();
    assert_eq!(back.thermal_tau_s, 0.0);
    assert!(!serde_json::to_string(&back)
        .unwrap()
        .contains("thermal_tau_s"));
    assert_eq!(pipeline_tau(&r), 0.0);
}

/// The calibration stamp: push writes the params file's hash (or the
/// record's, with `--record`) and the time, reads it back after the reset
/// with the board's store count; pull puts it into the file, and the
/// pulled file pushes again.
#[test]
fn push_stamps_the_calibration_and_pull_reads_the_stamp() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut r = rig(None);
    assert!(pull(&mut r.node, &r.cancel)
        .unwrap()
        .calibration_stamp
        .is_none());
    let t0 = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs() as u32;
    let rep = push(&mut r.node, &args(path.clone()), &r.cancel).unwrap();
    let st = rep.stamp.unwrap();
    // no record beside the file: one is written, and stamps the board
    let rec = perpend_calib::record::record_path(&path);
    assert_eq!(st.record_hash, record_hash(&std::fs::read(&rec).unwrap()));
    assert!((t0..t0 + 60).contains(&st.utc_s), "{st:?}");
    assert_eq!(st.store_count, 1);
    let text = rep.to_string();
    let line = format!("stamp {:08x} stored {}, store #1", st.record_hash, st.utc());
    assert!(text.contains(&line), "{text}");
    assert!(
        st.utc().ends_with('Z') && st.utc().starts_with("20"),
        "{st}"
    );
    // a second push, with a record beside the file
    let record = dir.path().join("record.json");
    std::fs::write(&record, b"{\"record\": 1}\n").unwrap();
    let a = args(path.clone());
    let st2 = push_with_record(&mut r.node, &a, Some(&record), &r.cancel)
        .unwrap()
        .stamp
        .unwrap();
    assert_eq!(st2.record_hash, record_hash(b"{\"record\": 1}\n"));
    assert_ne!(st2.record_hash, st.record_hash);
    assert_eq!(st2.store_count, 2);
    assert_eq!(read_stamp(&mut r.node).unwrap(), Some(st2));
    // pull writes it; pushing the pulled file puts that stamp back
    let back = pull(&mut r.node, &r.cancel).unwrap();
    let fs = back.calibration_stamp.clone().unwrap();
    assert_eq!(fs, st2.to_file());
    assert_eq!(fs.record_hash, format!("{:08x}", st2.record_hash));
    let p2 = dir.path().join("back.json");
    back.write(&p2).unwrap();
    assert!(std::fs::read_to_string(&p2)
        .unwrap()
        .contains("\"calibration_stamp\""));
    let rep = push(&mut r.node, &args(p2.clone()), &r.cancel).unwrap();
    assert_eq!(rep.changed, 0);
    let st3 = rep.stamp.unwrap();
    assert_eq!((st3.record_hash, st3.utc_s), (st2.record_hash, st2.utc_s));
    assert_eq!(st3.store_count, 3);
    // a missing record is refused before any write
    let missing = dir.path().join("missing.json");
    let e = push_with_record(&mut r.node, &args(path), Some(&missing), &r.cancel).unwrap_err();
    let e = format!("{e:#}");
    assert!(
        e.contains("missing.json: cannot read; nothing was written"),
        "{e}"
    );
    assert_eq!(read_stamp(&mut r.node).unwrap(), Some(st3));
}

/// A firmware without 0x2011: the push stores the calibration without a
/// stamp and says so; pull writes no stamp.
#[test]
fn a_firmware_without_the_stamp_is_pushed_without_one() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut r = rig_with(None, true, false);
    let rep = push(&mut r.node, &args(path), &r.cancel).unwrap();
    assert_eq!(rep.stamp, None);
    assert_eq!(r.board.lock().unwrap().app().stores(), 1);
    let text = rep.to_string();
    assert!(
        text.contains("no calibration stamp: the firmware of node 16")
            && text.contains("has no 0x2011"),
        "{text}"
    );
    assert_eq!(read_stamp(&mut r.node).unwrap(), None);
    assert!(pull(&mut r.node, &r.cancel)
        .unwrap()
        .calibration_stamp
        .is_none());
}

/// Spot coefficients exact in `f32` [mm per unit of tan²γ].
const SPOT: [f64; 2] = [0.375, -1.25];

/// The spot coefficients go to the board (sub 24/25), are read back in
/// the push's verification and come back in pull on their sensor only,
/// with "incidence" among the model's effects and no linearity table made
/// of them; a push without them clears the board's (the objects are what
/// the board applies).
#[test]
fn spot_terms_push_and_pull() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut f = ParamFile::read(&path).unwrap();
    f.sensors[2].ext.spot_mm = Some(SPOT);
    f.write(&path).unwrap();
    let mut r = rig(None);
    push(&mut r.node, &args(path.clone()), &r.cancel).unwrap();
    let back = pull(&mut r.node, &r.cancel).unwrap();
    assert_eq!(back.sensors[2].ext.spot_mm, Some(SPOT));
    assert!([0, 1, 3]
        .iter()
        .all(|&i| back.sensors[i].ext.spot_mm.is_none()));
    assert!(back.sensors.iter().all(|s| s.ext.linearity_table.is_none()));
    assert!(
        back.model.split('+').any(|m| m == "incidence"),
        "{}",
        back.model
    );
    let p = r
        .board
        .lock()
        .unwrap()
        .app()
        .device()
        .params(&Params::factory());
    assert_eq!(p.head.sensors[2].ext.spot, SPOT.map(|x| x as f32));
    f.sensors[2].ext.spot_mm = None;
    f.write(&path).unwrap();
    // only the two spot objects differ from what the board holds
    assert_eq!(
        push(&mut r.node, &args(path), &r.cancel).unwrap().changed,
        2
    );
    let back = pull(&mut r.node, &r.cancel).unwrap();
    assert!(back.sensors.iter().all(|s| s.ext.spot_mm.is_none()));
    assert!(!back.model.contains("incidence"), "{}", back.model);
}

/// A spot coefficient beyond the board's ±10 mm is named before any
/// write.
#[test]
fn a_spot_term_beyond_the_board_range_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let mut f = ParamFile::read(&params_file(dir.path(), 4)).unwrap();
    f.sensors[1].ext.spot_mm = Some([0.0, 10.5]);
    let e = format!("{:#}", plan(&f).unwrap_err());
    assert!(e.contains("sensor 2 spot sin"), "{e}");
}

/// A firmware before the spot objects (0x2101 sub 0 = 23): a file with
/// spot terms is refused before any write, naming sensor and firmware;
/// a file without them is pushed (sub 1..23) and pulled with none.
#[test]
fn spot_terms_for_a_firmware_without_them_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut f = ParamFile::read(&path).unwrap();
    let mut r = rig_with(None, false, true);
    f.sensors[3].ext.spot_mm = Some(SPOT);
    let spot_path = dir.path().join("spot.json");
    f.write(&spot_path).unwrap();
    let e = format!(
        "{:#}",
        push(&mut r.node, &args(spot_path), &r.cancel).unwrap_err()
    );
    assert!(
        e.contains("sensor 4") && e.contains("no spot objects"),
        "{e}"
    );
    assert!(e.contains("Nothing was written"), "{e}");
    assert_eq!(r.board.lock().unwrap().app().stores(), 0);
    let rep = push(&mut r.node, &args(path), &r.cancel).unwrap();
    assert_eq!(rep.values, 4 * 27 + 1);
    let back = pull(&mut r.node, &r.cancel).unwrap();
    assert!(back.sensors.iter().all(|s| s.ext.spot_mm.is_none()));
}

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
use perpend_lab::paramfile::{ParamFile, TableParams, TransferParams, TRANSFER_CURRENT};

use super::{plan, pull, push, PushArgs};
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
    PushArgs { file, preop: false }
}

#[test]
fn push_stores_and_pull_reads_the_same_values() {
    let dir = tempfile::tempdir().unwrap();
    let path = params_file(dir.path(), 4);
    let mut r = rig(None);
    let before = pull(&mut r.node, &r.cancel).unwrap();
    assert_eq!(before.model, "base");
    let rep = push(&mut r.node, &args(path.clone()), &r.cancel).unwrap();
    assert_eq!(rep.values, 4 * 27 + 1);
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
        e.contains("interrupted (Ctrl-C) after 20 of 109 writes"),
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
    assert_eq!(plan(&f).unwrap().len(), 4 * 27 + 1);
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

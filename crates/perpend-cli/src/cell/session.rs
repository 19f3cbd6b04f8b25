//! The board as a cell run found it and what the run changed on it
//! ([`Session`]): kept at the start (NMT state, residual limit, the
//! calibration in `DIR/previous.json`), changed by the before pass (the
//! residual limit raised) and the push, and put back in a fixed order
//! when the run stops ([`Session::restore`]: link, calibration, residual
//! limit, lock, NMT state).

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_calib::plan::PlannedPose;
use perpend_calib::record::BoardStamp;

use super::args::RunArgs;
use super::robot::Robot;
use super::verify::{verify, write_csv, Reference, Sampling, Verified};
use crate::canopen::{Nmt, NodeState};
use crate::node::{params, Node};

/// How far the push of the new calibration got.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum PushStage {
    /// Nothing written: the board holds its previous calibration.
    NotBegun,
    /// Begun: the board may hold anything until `previous.json` is back.
    Begun,
    /// Written, stored, reset, verified.
    Verified,
}

/// One run on one node and what it changed there, to put back
/// ([`Session::restore`]).
pub struct Session<'a> {
    pub(super) node: Node,
    pub(super) args: &'a RunArgs,
    pub(super) cancel: &'a AtomicBool,
    /// The heartbeat period found [ms] (0: off).
    pub(super) heartbeat_ms: u64,
    /// The NMT state found (`None`: heartbeat off, unknown).
    pub(super) nmt: Option<NodeState>,
    /// The residual limit 0x2300 sub 4 found [mm].
    pub(super) residual: f32,
    /// Whether the run holds the residual limit raised.
    pub(super) raised: bool,
    pub(super) push: PushStage,
    /// The board's calibration as found (`DIR/previous.json`).
    pub(super) previous: PathBuf,
    /// The before figure, once measured.
    pub(super) before_deg: Option<f64>,
    /// The board's serial (0x1018 sub 4) as `0x…`, for the record.
    pub(super) serial: String,
    /// Its software version (0x100A), for the record.
    pub(super) firmware: String,
    /// The stamp the board carries after the push (`None`: not pushed, or
    /// pushed back).
    pub(super) stamp: Option<BoardStamp>,
    /// The board's die temperature at the start and the end [°C].
    pub(super) die_temp_c: [Option<f64>; 2],
    /// The tolerance and the tracker.
    pub(super) reference: Reference,
    /// When the run began (ISO 8601 UTC), for the certificate.
    pub(super) started_utc: String,
}

/// What [`Session::restore`] put back, and what it could not.
#[derive(Debug, Default)]
pub(super) struct Restored {
    pub(super) done: Vec<String>,
    pub(super) problems: Vec<String>,
    /// `previous.json` was pushed back and verified.
    pub(super) reverted: bool,
}

impl<'a> Session<'a> {
    /// Notes the NMT state and the residual limit, keeps the calibration
    /// in `DIR/previous.json`. Changes nothing on the board.
    pub(super) fn begin(
        mut node: Node,
        args: &'a RunArgs,
        cancel: &'a AtomicBool,
        reference: Reference,
    ) -> Result<Self> {
        let started_utc = perpend_calib::record::utc_now();
        let heartbeat_ms = node.heartbeat_ms()?;
        let nmt = node.state(heartbeat_ms)?;
        let residual = node.client.read_f32(node.id, 0x2300, 4)?;
        let serial = format!("{:#010x}", node.client.read_u32(node.id, 0x1018, 4)?);
        let firmware = node.client.read_string(node.id, 0x100A, 0)?;
        let die = die_temp(&mut node);
        let previous = args.out.join("previous.json");
        params::pull(&mut node, cancel)
            .and_then(|f| f.write(&previous))
            .with_context(|| {
                format!(
                    "keeping the calibration of {} in {} before anything is changed (nothing \
                     was changed)",
                    node.name(),
                    previous.display()
                )
            })?;
        println!(
            "cell: the board's calibration kept in {} (pushed back if this run does not \
             end with a better one)",
            previous.display()
        );
        Ok(Self {
            node,
            args,
            cancel,
            heartbeat_ms,
            nmt,
            residual,
            raised: false,
            push: PushStage::NotBegun,
            previous,
            before_deg: None,
            serial,
            firmware,
            stamp: None,
            die_temp_c: [die, None],
            reference,
            started_utc,
        })
    }

    /// The verification's sampling.
    pub(super) fn sampling(&self) -> Sampling {
        self.args.m.sampling()
    }

    /// The before pass with the residual limit raised, put back after it;
    /// its poses go into `DIR/verify.csv`, its mean into the session.
    ///
    /// # Errors
    /// Bus, robot, Ctrl-C, a reset of the node, the residual limit.
    pub fn before(&mut self, robot: &mut Robot, fresh: &[PlannedPose]) -> Result<Verified> {
        let (id, a) = (self.node.id, self.args);
        let raised = (a.before_residual_mm as f32).max(self.residual);
        // Raised from the request on: a lost answer may hide a done write.
        self.raised = true;
        self.node
            .client
            .download(id, 0x2300, 4, &raised.to_le_bytes())
            .context("raising the residual limit (0x2300 sub 4) for the before pass")?;
        let sampling = self.sampling();
        let v = verify(
            &mut self.node,
            robot,
            fresh,
            sampling,
            "before",
            self.cancel,
        )?;
        self.put_back_residual()?;
        write_csv(&self.args.out.join("verify.csv"), "before", &v)?;
        let before = v.mean_deg();
        self.before_deg = Some(before);
        println!("cell: before calibration, normal error {before:.4}° (mean)");
        Ok(v)
    }

    /// The after pass on the freshly pushed calibration, at the same fresh
    /// poses; its poses go into `DIR/verify.csv`, the die temperature at
    /// the end into the session.
    ///
    /// # Errors
    /// Bus, robot, Ctrl-C, a reset of the node.
    pub fn after(&mut self, robot: &mut Robot, fresh: &[PlannedPose]) -> Result<Verified> {
        let sampling = self.sampling();
        let v = verify(&mut self.node, robot, fresh, sampling, "after", self.cancel)?;
        write_csv(&self.args.out.join("verify.csv"), "after", &v)?;
        self.die_temp_c[1] = die_temp(&mut self.node);
        Ok(v)
    }

    /// Writes the residual limit found back and reads it back.
    pub(super) fn put_back_residual(&mut self) -> Result<()> {
        let (id, old) = (self.node.id, self.residual);
        self.node
            .client
            .download(id, 0x2300, 4, &old.to_le_bytes())?;
        let v = self.node.client.read_f32(id, 0x2300, 4)?;
        if v.to_bits() != old.to_bits() {
            bail!("it reads {v} mm after {old} mm was written");
        }
        self.raised = false;
        Ok(())
    }

    /// Pushes the new calibration (verified push, `--preop`).
    pub(super) fn push_new(&mut self, params: &Path) -> Result<()> {
        self.push = PushStage::Begun;
        let push = params::PushArgs {
            file: params.to_path_buf(),
            preop: true,
            record: None,
        };
        let stamped = perpend_calib::record::record_path(params);
        let report = params::push(&mut self.node, &push, self.cancel).map_err(|e| {
            // What push says the board is left with is superseded by the
            // restore: its cause comes first.
            let left = e.to_string();
            let cause: Vec<String> = if left.starts_with("nothing was stored") {
                e.chain().skip(1).map(ToString::to_string).collect()
            } else {
                e.chain().map(ToString::to_string).collect()
            };
            anyhow!("pushing the new calibration: {}", cause.join(": "))
        })?;
        println!("{report}");
        self.push = PushStage::Verified;
        if let (Some(st), true) = (&report.stamp, stamped.exists()) {
            self.stamp = Some(BoardStamp {
                record_hash: format!("{:08x}", st.record_hash),
                stamped_record: perpend_calib::record::FileHash::of(&stamped)?,
                utc: crate::record::iso(f64::from(st.utc_s)),
                store_count: st.store_count,
            });
        }
        Ok(())
    }

    /// Reaches the node again: as it is, else over a new connection (once).
    pub(super) fn relink(&mut self) -> Result<()> {
        if self.node.hello().is_ok() {
            return Ok(());
        }
        // The old connection goes first: a board (the virtual one, an
        // slcan adapter) takes one client, and our own would lock us out.
        let mut closed = crate::bus::fake::FakeBus::new(crate::bus::fake::FnPeer(
            |_: &perpend_can::Frame, _: &mut Vec<perpend_can::Frame>| {},
        ));
        closed.closed = true;
        let id = self.node.id;
        let placeholder = Node::new(crate::canopen::Client::new(Box::new(closed)), id);
        drop(std::mem::replace(&mut self.node, placeholder));
        let mut node = Node::connect(&self.args.link)?;
        node.hello()?;
        self.node = node;
        Ok(())
    }

    /// Puts back what the run changed: link, calibration (when `revert`),
    /// residual limit, lock, NMT state; each step tried even when one
    /// before it failed (the link excepted).
    pub(super) fn restore(&mut self, revert: bool) -> Restored {
        let mut r = Restored::default();
        let name = self.node.name();
        if let Err(e) = self.relink() {
            r.problems.push(format!(
                "{name} cannot be reached to put back what the run changed ({e:#}); when it \
                 answers, {}",
                self.by_hand(revert)
            ));
            return r;
        }
        let id = self.node.id;
        if let Err(e) = self.node.client.nmt(id, Nmt::Preop) {
            r.problems
                .push(format!("{name}: pre-operational for the restore: {e}"));
        }
        if revert {
            self.revert(&mut r);
        }
        if self.raised {
            let old = self.residual;
            match self.put_back_residual() {
                Ok(()) => r.done.push(format!(
                    "residual limit 0x2300 sub 4 back to {old} mm (read back)"
                )),
                Err(e) => r.problems.push(format!(
                    "{name}: the residual limit 0x2300 sub 4 could not be put back to {old} mm \
                     ({e:#}); it is not stored: reset the node"
                )),
            }
        }
        self.relock(&mut r);
        self.restore_nmt(&mut r);
        r
    }

    /// Pushes `previous.json` back (the verified push).
    fn revert(&mut self, r: &mut Restored) {
        let quiet = AtomicBool::new(false);
        let push = params::PushArgs {
            file: self.previous.clone(),
            preop: true,
            record: None,
        };
        match params::push(&mut self.node, &push, &quiet) {
            Ok(_) => {
                self.push = PushStage::NotBegun;
                self.stamp = None;
                r.reverted = true;
                r.done.push(format!(
                    "the previous calibration ({}) pushed back: written, stored, reset, read \
                     back identical",
                    self.previous.display()
                ));
            }
            Err(e) => r.problems.push(format!(
                "pushing the previous calibration back failed ({e:#}): {}",
                self.by_hand(true)
            )),
        }
    }

    /// Locks calibration writes (0x2010) if they are unlocked.
    fn relock(&mut self, r: &mut Restored) {
        let id = self.node.id;
        match self.node.client.read_u32(id, 0x2010, 0) {
            Ok(0) => {}
            Ok(_) => match self.node.client.write_u32(id, 0x2010, 0, 0) {
                Ok(()) => r
                    .done
                    .push("calibration writes locked again (0x2010)".into()),
                Err(e) => r.problems.push(format!("locking 0x2010: {e}")),
            },
            Err(e) => r.problems.push(format!("reading the lock 0x2010: {e}")),
        }
    }

    /// Returns the node to the NMT state found and checks its heartbeat.
    fn restore_nmt(&mut self, r: &mut Restored) {
        let id = self.node.id;
        let (cmd, want) = match self.nmt {
            Some(NodeState::Operational) => (Some(Nmt::Start), NodeState::Operational),
            Some(NodeState::Stopped) => (Some(Nmt::Stop), NodeState::Stopped),
            _ => (None, NodeState::PreOperational),
        };
        if let Some(c) = cmd {
            if let Err(e) = self.node.client.nmt(id, c) {
                r.problems.push(format!("NMT {want} again: {e}"));
                return;
            }
        }
        if self.heartbeat_ms == 0 {
            r.done
                .push("node left pre-operational (heartbeat off: state found unknown)".into());
            return;
        }
        let wait = Duration::from_millis(self.heartbeat_ms * 3 / 2 + 200);
        match self.node.client.wait_heartbeat(id, wait) {
            Ok(Some(s)) if s == want => r.done.push(format!("node {want} as found")),
            Ok(s) => r.problems.push(format!(
                "{}: should be {want} as found, its heartbeat says {}; set it with `perpend \
                 node … nmt`",
                self.node.name(),
                s.map_or("nothing".into(), |s| s.to_string())
            )),
            Err(e) => r.problems.push(format!("checking the NMT state: {e}")),
        }
    }

    /// What to do by hand when the restore cannot.
    pub(super) fn by_hand(&self, revert: bool) -> String {
        let mut s = String::from("reset it (its residual limit is not stored)");
        if revert || self.push != PushStage::NotBegun {
            s = format!(
                "push the previous calibration back: perpend node --bus {} --node-id {} push \
                 {} --preop",
                self.args.link.bus.as_deref().unwrap_or("BUS"),
                self.node.id,
                self.previous.display()
            );
        }
        s
    }
}

/// The board's die temperature (0x200A) [°C], `None` when it has none.
fn die_temp(node: &mut Node) -> Option<f64> {
    let t = node.client.read_f32(node.id, 0x200A, 0).ok()?;
    (t > perpend_can::od::DIE_TEMP_UNKNOWN).then_some(f64::from(t))
}

//! The device side of the LSS slave ([`crate::lss`], CiA 305): feeds it
//! the frames on 0x7E5, carries out its outcomes on the dictionary and the
//! store request, keeps a non-configured node silent, and times the
//! bit-rate switch.
//!
//! * **Pending node-id** = 0x2400 sub 1 (what an SDO write sets too):
//!   LSS "configure node-id" writes it; it becomes active at the next NMT
//!   reset communication or reset node.
//! * **Non-configured node**: 0x2400 sub 1 = 0xFF when the node starts
//!   (power-on, reset): it stays in NMT initialisation, sends nothing (no
//!   boot-up, heartbeat, EMCY, SDO or PDO) and serves LSS only, plus the
//!   NMT reset commands addressed to all nodes. When the LSS master gives
//!   it a node-id and switches it back to waiting state it continues its
//!   start-up at once (reset communication: boot-up with the new node-id).
//! * **Store configuration** stores 0x2400 only: sub 1 the pending
//!   node-id, sub 2 the configured (or active) bit rate; the other stored
//!   objects keep their stored values. The answer follows the storage
//!   outcome ([`Device::finish_request`]).
//! * **Activate bit timing** with switch delay d: from the request on the
//!   device sends nothing and ignores what it receives; after d it writes
//!   the new rate to 0x2400 sub 2 and hands it to the application once
//!   ([`Device::take_bit_rate_switch`]), which re-programs the controller;
//!   after another d it runs again.

use super::{Device, NmtState, Request};
use crate::frame::Frame;
use crate::lss::{self, Context, LssSlave, Outcome, UNCONFIGURED};

/// A bit-rate switch in progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Switch {
    kbps: u16,
    at_us: u64,
    silent_until_us: u64,
    done: bool,
}

/// Run-time LSS state of a device.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) struct LssRt {
    slave: LssSlave,
    switch: Option<Switch>,
    /// A switched bit rate the application has not taken yet.
    switched: Option<u16>,
    /// The node started non-configured (0x2400 sub 1 was 0xFF): it stays
    /// so, whatever LSS configures, until its next reset.
    unconfigured: bool,
}

impl Device {
    /// Whether the node is non-configured (CiA 305): started with node-id
    /// 0xFF in 0x2400 sub 1, it waits in NMT initialisation for LSS.
    pub fn lss_unconfigured(&self) -> bool {
        self.core.state == NmtState::Initialising
            && (self.lss.unconfigured || self.core.get(0x2400, 1) == u32::from(UNCONFIGURED))
    }

    /// Latches the non-configured start (see [`LssRt::unconfigured`]).
    fn latch(&mut self) {
        self.lss.unconfigured = self.lss_unconfigured();
    }

    /// NMT reset (node or communication) requested by LSS or by an NMT
    /// command to a non-configured node: the pending node-id is read again.
    fn lss_reset(&mut self, node: bool) {
        self.sdo.reset();
        self.lss.unconfigured = false;
        if node {
            self.core.reset_node();
        } else {
            self.core.reset_comm();
        }
    }

    /// The active node-id as LSS reports it: [`UNCONFIGURED`] for a
    /// non-configured node, else [`Device::node_id`].
    pub fn active_node_id(&self) -> u8 {
        if self.lss_unconfigured() {
            UNCONFIGURED
        } else {
            self.core.node_id
        }
    }

    /// What LSS "configure node-id" does, for factory tooling (the virtual
    /// board's non-configured start): `id` (1..127, or [`UNCONFIGURED`])
    /// becomes the pending node-id 0x2400 sub 1, active at the next reset;
    /// `false` (nothing changed) for another value.
    pub fn set_pending_node_id(&mut self, id: u8) -> bool {
        if !((1..=127).contains(&id) || id == UNCONFIGURED) {
            return false;
        }
        self.core.set(0x2400, 1, u32::from(id));
        self.core.config_changed();
        true
    }

    /// The LSS state (waiting or configuration).
    pub fn lss_state(&self) -> lss::LssState {
        self.lss.slave.state()
    }

    /// The bit rate \[kbit/s\] the CAN controller must switch to now, once
    /// per LSS "activate bit timing" (after its switch delay; the device
    /// stays silent for another delay).
    pub fn take_bit_rate_switch(&mut self) -> Option<u16> {
        self.lss.switched.take()
    }

    fn lss_context(&self) -> Context {
        let id = |k: u8| self.core.get(0x1018, k);
        Context {
            identity: [id(1), id(2), id(3), id(4)],
            active_node_id: self.active_node_id(),
            pending_node_id: self.core.get(0x2400, 1) as u8,
            bit_rate_kbps: self.core.get(0x2400, 2) as u16,
        }
    }

    fn silent(&self, now_us: u64) -> bool {
        self.lss.switch.is_some_and(|s| now_us < s.silent_until_us)
    }

    /// The LSS part of [`Device::handle`]: `true` when the frame was
    /// consumed (an LSS request, anything during a bit-rate switch,
    /// anything but NMT reset for a non-configured node).
    pub(super) fn lss_handle(
        &mut self,
        frame: &Frame,
        now_us: u64,
        out: &mut impl FnMut(Frame),
    ) -> bool {
        if self.silent(now_us) {
            return true;
        }
        self.latch();
        if frame.id == lss::MASTER_ID {
            let ctx = self.lss_context();
            if let Some(o) = self.lss.slave.handle(frame.payload(), &ctx) {
                self.lss_outcome(o, now_us, out);
            }
            return true;
        }
        if !self.lss_unconfigured() {
            return false;
        }
        // NMT reset node / communication to all nodes: the pending
        // node-id is read again.
        if let (0x000, &[cs @ (0x81 | 0x82), 0, ..]) = (frame.id, frame.payload()) {
            self.lss_reset(cs == 0x81);
        }
        true
    }

    fn lss_outcome(&mut self, o: Outcome, now_us: u64, out: &mut impl FnMut(Frame)) {
        let mut reply = |d: [u8; 8]| out(Frame::new(lss::SLAVE_ID, &d));
        match o {
            Outcome::Reply(d) => reply(d),
            Outcome::NodeId(id) => {
                self.set_pending_node_id(id);
                reply(lss::reply_code(lss::cs::CONFIGURE_NODE_ID, lss::ERR_NONE));
            }
            Outcome::Activate { kbps, delay_ms } => {
                let d = u64::from(delay_ms) * 1000;
                self.lss.slave.activated();
                self.lss.switch = Some(Switch {
                    kbps,
                    at_us: now_us.saturating_add(d),
                    silent_until_us: now_us.saturating_add(2 * d),
                    done: false,
                });
                self.lss_poll(now_us);
            }
            Outcome::Store { kbps } => {
                if self.core.request.is_some() {
                    reply(LssSlave::store_done(false));
                } else {
                    self.core.request = Some(Request::StoreLss {
                        bit_rate_kbps: kbps,
                    });
                    self.core.event(super::Events::REQUEST);
                }
            }
            Outcome::Waiting => {
                let pending = self.core.get(0x2400, 1);
                if self.lss_unconfigured() && (1..=127).contains(&pending) {
                    self.lss_reset(false);
                }
            }
        }
    }

    /// The LSS part of [`Device::poll`]: carries out a due bit-rate switch;
    /// `true` while the device must stay silent (switch in progress, or
    /// non-configured).
    pub(super) fn lss_poll(&mut self, now_us: u64) -> bool {
        if let Some(mut s) = self.lss.switch {
            if !s.done && now_us >= s.at_us {
                s.done = true;
                self.core.set(0x2400, 2, u32::from(s.kbps));
                self.lss.switched = Some(s.kbps);
            }
            self.lss.switch = (now_us < s.silent_until_us).then_some(s);
            if self.lss.switch.is_some() {
                return true;
            }
        }
        self.latch();
        self.lss.unconfigured
    }
}

/// The LSS answer to a store request that finished (`ok`: stored).
pub(super) const fn store_done(ok: bool) -> [u8; 8] {
    LssSlave::store_done(ok)
}

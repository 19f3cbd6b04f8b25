//! SYNC counter and SYNC-locked acquisition, heartbeat consumer, error
//! behaviour and the command RPDO of the [`Device`] (a child module of
//! `device`: it extends `Core` and `Device`).
//!
//! * **SYNC counter** (CiA 301 §7.2.5, 0x1019): with an overflow value of
//!   2..=240 the SYNC carries a one-byte counter; a TPDO of type 1..=240
//!   with a non-zero *SYNC start value* (0x180x sub 6) is sent first at the
//!   SYNC whose counter equals it, then every `type`-th SYNC. A SYNC whose
//!   length does not match 0x1019 (DLC 0 without counter, 1 with one) is
//!   ignored as CANopenNode does: no TPDO, nothing counted towards a
//!   transmission type or start value; it raises EMCY 0x8240 (unexpected
//!   SYNC data length, in pre-operational too) until a matching one
//!   arrives.
//! * **SYNC-locked acquisition** (0x2301 sub 1 = [`TRIGGER_SYNC`]): each
//!   SYNC asks the application for one scan ([`Events::SYNC_SAMPLE`]); the
//!   synchronous TPDOs due at that SYNC wait for that sample and carry it
//!   ([`Device::poll`] sends them once it is published). A SYNC that
//!   arrives before the previous one's sample counts one miss (0x2301
//!   sub 2) and its waiting TPDOs are dropped: never a duplicate, never a
//!   stale sample. With the timer trigger the TPDOs go out at the SYNC
//!   with the latest sample, as before.
//! * **Heartbeat consumer** (§7.2.8.3.2, 0x1016 sub 1..=[`HB_CONSUMERS`]:
//!   node-id in bits 16-23, time in ms in bits 0-15): monitoring of a node
//!   starts with its first heartbeat (or boot-up); no heartbeat for the
//!   consumer time raises EMCY 0x8130 (heartbeat error, data `[node-id]`)
//!   and the communication-error reaction; the next heartbeat clears it.
//!   Two subs with the same node-id and non-zero times are refused
//!   (0x06040043).
//! * **Error behaviour** (§7.5.2.32, 0x1029 sub 1) on a communication
//!   error (heartbeat lost, bus-off): 0 operational → pre-operational,
//!   1 no state change, 2 → stopped (from pre-operational too). The EMCY
//!   of the error is sent before the state changes (in stopped nothing is
//!   sent).
//! * **Command RPDO** (RPDO1, 0x1400 / 0x1600, default COB-ID 0x200 +
//!   node-id, transmission type 254/255): its first byte is written to the
//!   command object 0x2500 in operational; [`CMD_CAPTURE`] raises
//!   [`Events::COMMAND`] for the application (which averages 0x2501
//!   samples into 0x2502). A frame without data raises EMCY 0x8210 (PDO
//!   not processed due to length error); other command values are ignored.
//!   Node guarding is not offered (docs/can.md: it needs remote frames,
//!   which CiA recommends against; the heartbeat consumer covers it).
//!
//! Limits: one RPDO with a fixed mapping; two heartbeat consumers; the
//! synchronous window length (0x1007) is not implemented.

use super::{Core, Device, Events, NmtState, Written};
use crate::frame::Frame;
use crate::od::{slot_of, CMD_CAPTURE, CMD_NONE, HB_CONSUMERS, TPDOS, TRIGGER_SYNC};
use crate::sdo::SdoAbort;
use crate::status::error_register;

/// EMCY: unexpected SYNC data length (CiA 301 table 26).
pub const EMCY_SYNC_LENGTH: u16 = 0x8240;
/// EMCY: life guard or heartbeat error.
pub const EMCY_HEARTBEAT: u16 = 0x8130;
/// EMCY: PDO not processed due to length error.
pub const EMCY_PDO_LENGTH: u16 = 0x8210;

/// SYNC state of the SYNC-locked acquisition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) struct SyncRt {
    /// TPDOs (bit k) due at the last SYNC, waiting for its sample.
    pub(super) due: u8,
    /// Which of them are acyclic (type 0: sent only if changed).
    pub(super) acyclic: u8,
    /// A SYNC is waiting for its sample.
    pub(super) waiting: bool,
    /// The sample of the last SYNC has been published.
    pub(super) sampled: bool,
}

/// One heartbeat consumer's monitor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) struct HbMonitor {
    /// When the monitored node's last heartbeat arrived \[µs\].
    pub(super) last: Option<u64>,
    /// Its timeout was reported and not yet cleared.
    pub(super) lost: bool,
}

/// Value slots of the objects on the SYNC path (compile-time constants).
const SYNC_OVERFLOW: usize = slot_of(0x1019, 0);
const TRIGGER: usize = slot_of(0x2301, 1);
const RPDO_COB: usize = slot_of(0x1400, 1);
const SAMPLE_TIME: usize = slot_of(0x2020, 0);
pub(super) const TPDO_COB: [usize; TPDOS] = [
    slot_of(0x1800, 1),
    slot_of(0x1801, 1),
    slot_of(0x1802, 1),
    slot_of(0x1803, 1),
];
pub(super) const TPDO_MAP: [usize; TPDOS] = [
    slot_of(0x1A00, 0),
    slot_of(0x1A01, 0),
    slot_of(0x1A02, 0),
    slot_of(0x1A03, 0),
];
pub(super) const TPDO_TYPE: [usize; TPDOS] = [
    slot_of(0x1800, 2),
    slot_of(0x1801, 2),
    slot_of(0x1802, 2),
    slot_of(0x1803, 2),
];

impl Core {
    /// The value of a constant slot (always in range: the slots come from
    /// the table the values array is sized by).
    pub(super) fn at(&self, s: usize) -> u32 {
        self.values.get(s).copied().unwrap_or(0)
    }

    fn sync_locked(&self) -> bool {
        self.at(TRIGGER) == TRIGGER_SYNC as u32
    }

    /// The counter of a SYNC with payload `p` (`Some(None)` without
    /// counter), keeping EMCY 0x8240 in step with its length; `None` when
    /// the length does not match 0x1019 (DLC 0 without counter, 1 with
    /// one): such a frame is no SYNC. As CANopenNode's `CO_SYNC_receive`,
    /// which sets a receive error instead of the SYNC flag (reported as
    /// `CO_EMC_SYNC_DATA_LENGTH` by `CO_SYNC_process`).
    fn sync_counter(&mut self, p: &[u8]) -> Option<Option<u8>> {
        let with_counter = self.at(SYNC_OVERFLOW) >= 2;
        if p.len() != usize::from(with_counter) {
            self.raise(
                EMCY_SYNC_LENGTH,
                error_register::COMMUNICATION,
                [p.len() as u8, 0, 0, 0, 0],
            );
            return None;
        }
        self.clear(EMCY_SYNC_LENGTH);
        Some(p.first().copied().filter(|_| with_counter))
    }

    /// Whether TPDO `k` of transmission type `tt` is due at a SYNC with
    /// `counter` (`None`: no counter; type 0: decided when it is sent, by a
    /// change of its data).
    fn sync_due(&mut self, k: usize, tt: u32, counter: Option<u8>) -> bool {
        if tt == 0 {
            return true;
        }
        if !(1..=240).contains(&tt) {
            return false;
        }
        let start = match counter {
            Some(_) => self.get(0x1800 + k as u16, 6),
            None => 0,
        };
        let rt = &mut self.tpdo[k];
        if start != 0 && !rt.started {
            if counter != Some(start as u8) {
                return false;
            }
            rt.started = true;
            rt.sync_count = 0;
            return true;
        }
        let rt = &mut self.tpdo[k];
        rt.sync_count = rt.sync_count.saturating_add(1);
        if u32::from(rt.sync_count) >= tt {
            rt.sync_count = 0;
            true
        } else {
            false
        }
    }

    /// Sends the synchronous TPDOs in `due` (the acyclic ones, bits of
    /// `acyclic`, only when their data changed).
    fn send_due(&mut self, due: u8, acyclic: u8, now_us: u64, out: &mut impl FnMut(Frame)) {
        for k in 0..TPDOS {
            if due & (1 << k) == 0 {
                continue;
            }
            if acyclic & (1 << k) == 0 || core::mem::take(&mut self.tpdo[k].event_pending) {
                self.send_tpdo(k, now_us, out);
            }
        }
    }

    /// SYNC-locked: sends what waits for a published sample; a SYNC still
    /// waiting when the next one comes counts as missed (0x2301 sub 2).
    fn settle_sync(&mut self, now_us: u64, next_sync: bool, out: &mut impl FnMut(Frame)) {
        let s = self.syncs;
        if s.sampled && s.due != 0 {
            self.syncs.due = 0;
            self.send_due(s.due, s.acyclic, now_us, out);
        }
        if next_sync && s.waiting {
            let missed = self.get(0x2301, 2).wrapping_add(1);
            self.set(0x2301, 2, missed);
            self.syncs = super::SyncRt::default();
        }
    }

    /// The communication-error reaction of 0x1029 sub 1; queued EMCYs go
    /// out first (nothing is sent in stopped). CiA 301 §7.5.2.32 limits
    /// only value 0 to operational: value 2 stops a pre-operational node
    /// too. (CANopenNode's `CO_NMT_process` reacts in operational only,
    /// with its compile-time `NMTcontrol` instead of 0x1029; CiA 301 is
    /// not ambiguous here, so the device follows it.)
    fn comm_error(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        let next = match (self.get(0x1029, 1), self.state) {
            (0, NmtState::Operational) => NmtState::PreOperational,
            (2, NmtState::Operational | NmtState::PreOperational) => NmtState::Stopped,
            _ => return,
        };
        self.send_emcys(now_us, out);
        self.set_state(next);
    }

    /// A heartbeat (or boot-up) of `node` at `now_us`.
    fn heartbeat_in(&mut self, node: u8, now_us: u64) {
        for i in 0..HB_CONSUMERS {
            let v = self.get(0x1016, i as u8 + 1);
            if v & 0xFFFF == 0 || (v >> 16) as u8 != node {
                continue;
            }
            self.hb_cons[i].last = Some(now_us);
            if self.hb_cons[i].lost {
                self.hb_cons[i].lost = false;
                if !self.hb_cons.iter().any(|m| m.lost) {
                    self.clear(EMCY_HEARTBEAT);
                }
            }
        }
    }

    /// Heartbeats overdue at `now_us`: EMCY 0x8130 and the reaction.
    fn check_heartbeats(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        for i in 0..HB_CONSUMERS {
            let v = self.get(0x1016, i as u8 + 1);
            let time_us = u64::from(v & 0xFFFF) * 1000;
            let m = self.hb_cons[i];
            let overdue = m.last.is_some_and(|t| now_us > t + time_us);
            if time_us == 0 || m.lost || !overdue {
                continue;
            }
            self.hb_cons[i].lost = true;
            let node = (v >> 16) as u8;
            self.raise(
                EMCY_HEARTBEAT,
                error_register::COMMUNICATION,
                [node, 0, 0, 0, 0],
            );
            self.comm_error(now_us, out);
        }
    }

    /// 0x1016 sub `sub` = `v`: one node-id per consumer (0x06040043).
    pub(super) fn write_hb_consumer(
        &mut self,
        sub: u8,
        v: u32,
    ) -> Result<Option<Written>, SdoAbort> {
        let node = (v >> 16) & 0xFF;
        let clash = (1..=HB_CONSUMERS as u8).any(|s| {
            let o = self.get(0x1016, s);
            s != sub && v & 0xFFFF != 0 && o & 0xFFFF != 0 && (o >> 16) & 0xFF == node
        });
        if clash || node > 127 {
            return Err(SdoAbort::Incompatible);
        }
        self.set(0x1016, sub, v);
        if let Some(m) = self.hb_cons.get_mut(sub as usize - 1) {
            *m = HbMonitor::default();
        }
        if !self.hb_cons.iter().any(|m| m.lost) {
            self.clear(EMCY_HEARTBEAT);
        }
        Ok(Some(Written::Done))
    }

    /// RPDO1 communication parameter `sub` = `v` (the TPDO rules: COB-ID
    /// bits 0-30 only while the RPDO does not exist).
    pub(super) fn write_rpdo_comm(&mut self, sub: u8, v: u32) -> Result<Option<Written>, SdoAbort> {
        if sub != 1 {
            return Ok(None);
        }
        let old = self.get(0x1400, 1);
        // Bit 30 is reserved for an RPDO (CiA 301 Table 70: "don't care");
        // CANopenNode (OD_write_14xx) accepts it either way, and so do we.
        // Bit 29 (a 29-bit identifier) and bits 11..28 are refused.
        if v & 0x2000_0000 != 0 || v & 0x1FFF_F800 != 0 {
            return Err(SdoAbort::Range);
        }
        if v & 0x8000_0000 == 0 {
            if !super::cob_allowed(v & 0x7FF) {
                return Err(SdoAbort::Range);
            }
            if old & 0x8000_0000 == 0 && old & 0x3FFF_FFFF != v & 0x3FFF_FFFF {
                return Err(SdoAbort::Range);
            }
        }
        self.set(0x1400, 1, v);
        Ok(Some(Written::Done))
    }

    /// The command 0x2500 = `v` (SDO or RPDO).
    pub(super) fn command(&mut self, v: u32) -> Result<Option<Written>, SdoAbort> {
        if self.rom_loader_locked && v == u32::from(crate::od::CMD_BOOTLOADER) {
            return Err(SdoAbort::State);
        }
        self.set(0x2500, 0, v);
        self.event(Events::COMMAND);
        Ok(Some(Written::Done))
    }

    /// The COB-ID RPDO1 listens on, if it exists.
    pub(super) fn rpdo_cob(&self) -> Option<u16> {
        let v = self.at(RPDO_COB);
        (v & 0x8000_0000 == 0).then_some((v & 0x7FF) as u16)
    }
}

impl Device {
    /// A SYNC with payload `p` at `now_us` (module docs).
    pub(super) fn sync(&mut self, p: &[u8], now_us: u64, out: &mut impl FnMut(Frame)) {
        let c = &mut self.core;
        // The length is checked in pre-operational too (CANopenNode:
        // `NMTisPreOrOperational`); only operational sends PDOs.
        if !matches!(c.state, NmtState::Operational | NmtState::PreOperational) {
            return;
        }
        let Some(counter) = c.sync_counter(p) else {
            return; // wrong length: no PDO, nothing counted
        };
        if c.state != NmtState::Operational {
            return;
        }
        let locked = c.sync_locked();
        if locked {
            c.settle_sync(now_us, true, out);
        }
        let (mut due, mut acyclic) = (0u8, 0u8);
        for k in 0..TPDOS {
            if c.at(TPDO_COB[k]) & 0x8000_0000 != 0 {
                continue;
            }
            let tt = c.at(TPDO_TYPE[k]);
            if c.sync_due(k, tt, counter) {
                due |= 1 << k;
                acyclic |= u8::from(tt == 0) << k;
            }
        }
        if locked {
            c.syncs = super::SyncRt {
                due,
                acyclic,
                waiting: true,
                sampled: false,
            };
            c.event(Events::SYNC_SAMPLE);
        } else {
            c.send_due(due, acyclic, now_us, out);
        }
    }

    /// What [`Device::poll`] does for this module: the TPDOs waiting for
    /// a SYNC's sample, and overdue heartbeats.
    pub(super) fn poll_sync(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        let c = &mut self.core;
        if c.state == NmtState::Operational && c.sync_locked() {
            c.settle_sync(now_us, false, out);
        }
        c.check_heartbeats(now_us, out);
    }

    /// Frames of this module: heartbeats of consumed nodes and RPDO1.
    /// Returns whether `frame` was one of them.
    pub(super) fn handle_sync(&mut self, frame: &Frame, now_us: u64) -> bool {
        let p = frame.payload();
        let c = &mut self.core;
        if (0x701..=0x77F).contains(&frame.id) && p.len() == 1 {
            c.heartbeat_in((frame.id - 0x700) as u8, now_us);
            return true;
        }
        if c.rpdo_cob() != Some(frame.id) {
            return false;
        }
        if c.state == NmtState::Operational {
            match p.first() {
                None => {
                    c.raise(
                        EMCY_PDO_LENGTH,
                        error_register::COMMUNICATION,
                        [0, 1, 0, 0, 0],
                    );
                }
                Some(&cmd) if cmd == CMD_CAPTURE || cmd == CMD_NONE => {
                    c.clear(EMCY_PDO_LENGTH);
                    let _ = c.command(u32::from(cmd));
                }
                Some(_) => {}
            }
        }
        true
    }

    /// The sample of the current SYNC (SYNC-locked) or of the timer has
    /// been taken at `t_us`: 0x2020 and, when a SYNC waits, its TPDOs are
    /// released at the next [`Device::poll`]. Call before
    /// [`Device::publish`].
    pub fn set_sample_time(&mut self, t_us: u64) {
        let c = &mut self.core;
        if let Some(v) = c.values.get_mut(SAMPLE_TIME) {
            *v = t_us as u32;
        }
        if c.syncs.waiting {
            c.syncs.waiting = false;
            c.syncs.sampled = true;
        }
    }

    /// A communication error the application detected (bus-off): the
    /// reaction of 0x1029 sub 1.
    pub fn communication_error(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        self.core.comm_error(now_us, out);
    }

    /// Whether acquisition is locked to SYNC (0x2301 sub 1).
    pub fn sync_locked(&self) -> bool {
        self.core.sync_locked()
    }

    /// SYNCs whose sample came too late (0x2301 sub 2).
    pub fn sync_missed(&self) -> u32 {
        self.core.get(0x2301, 2)
    }

    /// Whether 0x2500 = [`crate::od::CMD_BOOTLOADER`] is accepted (the
    /// default) or refused with SDO abort 0x08000022 (the bootloader of a
    /// release build without the provisioning flag forbids the ROM loader).
    pub fn set_rom_loader_allowed(&mut self, allowed: bool) {
        self.core.rom_loader_locked = !allowed;
    }

    /// The command waiting in 0x2500 ([`CMD_NONE`] when none).
    pub fn command(&self) -> u8 {
        self.core.get(0x2500, 0) as u8
    }

    /// Samples a capture averages (0x2501).
    pub fn capture_samples(&self) -> u16 {
        self.core.get(0x2501, 0) as u16
    }

    /// Publishes a finished capture into 0x2502 (θ1, θ2, θ, pitch, yaw
    /// \[deg\], samples used), counts it (sub 7) and clears the command
    /// 0x2500; TPDOs of type 254/255 mapping 0x2502 see the change.
    pub fn finish_capture(&mut self, angles_deg: [f32; 5], used: u16) {
        let c = &mut self.core;
        c.set_run(0x2502, 1, &angles_deg.map(f32::to_bits));
        c.set(0x2502, 6, u32::from(used));
        let n = c.get(0x2502, 7).wrapping_add(1) & 0xFFFF;
        c.set(0x2502, 7, n);
        c.set(0x2500, 0, u32::from(CMD_NONE));
        c.mark_changed_tpdos();
    }
}

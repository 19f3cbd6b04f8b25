//! Receive acceptance filters of the FDCAN and a model of the receive path
//! (issue 11 item 3).
//!
//! [`RxSet`] is what the node consumes (CiA 301 predefined connection set,
//! §7.3.5, and CiA 305 LSS): NMT 0x000, SYNC (0x1005, 0x080), the SDO
//! request 0x600 + node-id, the RPDO COB-IDs (0x1400.. sub 1, bit 31 =
//! not valid), the heartbeats of the consumed nodes (0x1016: 0x700 + id)
//! and the LSS master 0x7E5. [`filters`] turns it into the FDCAN's
//! standard-id filter elements (RM0440 §44.3.8 and §44.4.23: at most
//! [`MAX_STD_FILTERS`] = 28, "dual ID" elements of two exact identifiers,
//! SFEC "store in FIFO 0/1"); the global filter rejects everything else
//! (RXGFC.ANFS = ANFE = reject, RRFS = RRFE = 1: remote frames too, no
//! object is offered by RTR). Time-critical frames (NMT, SYNC, RPDO) go to
//! Rx FIFO 0, the rest (SDO, LSS, heartbeats) to Rx FIFO 1, so that an SDO
//! flood can never push a SYNC out of a full FIFO.
//!
//! [`RxPath`] models the receive side for the host: both 3-element
//! hardware FIFOs (RM0440 §44.3.3) and the RAM ring the firmware's FDCAN
//! interrupt fills, with or without the interrupt able to run (a flash
//! operation inside a critical section blocks it, see
//! `docs/reliability.md`).
//!
//! Limits: classic CAN, 11-bit identifiers; the firmware reprograms the
//! elements while the controller runs (a frame arriving during the few
//! register writes may be filtered by the old or the new set).

use heapless::{Deque, Vec};

/// Standard-id filter elements of the STM32G4 FDCAN (RM0440 §44.3.3).
pub const MAX_STD_FILTERS: usize = 28;
/// RPDOs the node can have.
pub const MAX_RPDOS: usize = 4;
/// Heartbeat producers the node can consume.
pub const MAX_HEARTBEATS: usize = 8;
/// Elements of each hardware Rx FIFO on the STM32G4 (RM0440 §44.3.3).
pub const HW_FIFO: usize = 3;
/// LSS master request identifier (CiA 305).
pub const LSS_MASTER: u16 = 0x7E5;

/// Errors of this module.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RxFilterError {
    /// More identifiers than [`MAX_STD_FILTERS`] dual elements hold.
    TooMany,
}

/// Destination of an accepted frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fifo {
    /// Rx FIFO 0: NMT, SYNC, RPDOs.
    F0,
    /// Rx FIFO 1: SDO, LSS, heartbeats.
    F1,
}

/// One standard filter element: accept `ids` (one or two exact
/// identifiers, "dual ID" filter) into `fifo`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StdFilter {
    /// First identifier.
    pub id1: u16,
    /// Second identifier (equal to `id1` for a single one).
    pub id2: u16,
    /// Where matching frames go.
    pub fifo: Fifo,
}

impl StdFilter {
    /// The element's 32-bit word in the message RAM (RM0440 §44.3.8:
    /// SFT = 01 dual ID, SFEC = 001/010, SFID1, SFID2).
    pub fn word(&self) -> u32 {
        let sfec = match self.fifo {
            Fifo::F0 => 0b001,
            Fifo::F1 => 0b010,
        };
        (0b01 << 30)
            | (sfec << 27)
            | (u32::from(self.id1 & 0x7FF) << 16)
            | u32::from(self.id2 & 0x7FF)
    }
}

/// What the node listens to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RxSet {
    /// Node-id 1..=127; anything else (LSS "unconfigured" 0xFF) has no SDO
    /// server.
    pub node_id: u8,
    /// COB-ID of SYNC (0x1005).
    pub sync: u16,
    /// Valid RPDO COB-IDs.
    pub rpdos: [Option<u16>; MAX_RPDOS],
    /// Node-ids whose heartbeat is consumed (0x1016).
    pub heartbeats: [Option<u8>; MAX_HEARTBEATS],
    /// Listen to the LSS master.
    pub lss: bool,
}

impl RxSet {
    /// The identifiers with their FIFO, in a fixed order, duplicates
    /// removed (the first FIFO wins).
    pub fn ids(&self) -> Vec<(u16, Fifo), 24> {
        let mut v: Vec<(u16, Fifo), 24> = Vec::new();
        let mut add = |id: u16, f: Fifo| {
            if id <= 0x7FF && !v.iter().any(|&(x, _)| x == id) {
                let _ = v.push((id, f));
            }
        };
        add(0x000, Fifo::F0);
        add(self.sync, Fifo::F0);
        for id in self.rpdos.iter().flatten() {
            add(*id, Fifo::F0);
        }
        if (1..=127).contains(&self.node_id) {
            add(0x600 + u16::from(self.node_id), Fifo::F1);
        }
        if self.lss {
            add(LSS_MASTER, Fifo::F1);
        }
        for n in self.heartbeats.iter().flatten() {
            if (1..=127).contains(n) {
                add(0x700 + u16::from(*n), Fifo::F1);
            }
        }
        v
    }
}

/// The filter elements for `set`: identifiers of the same FIFO paired in
/// dual-ID elements.
///
/// # Errors
/// [`RxFilterError::TooMany`] when they do not fit (cannot happen with the
/// limits above: at most 24 identifiers in 28 elements).
pub fn filters(set: &RxSet) -> Result<Vec<StdFilter, MAX_STD_FILTERS>, RxFilterError> {
    let mut out: Vec<StdFilter, MAX_STD_FILTERS> = Vec::new();
    for fifo in [Fifo::F0, Fifo::F1] {
        let ids: Vec<u16, 24> = set
            .ids()
            .iter()
            .filter(|&&(_, f)| f == fifo)
            .map(|&(id, _)| id)
            .collect();
        for pair in ids.chunks(2) {
            let (id1, id2) = match pair {
                [a, b] => (*a, *b),
                [a] => (*a, *a),
                _ => continue,
            };
            out.push(StdFilter { id1, id2, fifo })
                .map_err(|_| RxFilterError::TooMany)?;
        }
    }
    Ok(out)
}

/// Where the hardware would put a data frame with identifier `id`, or
/// `None` when the global filter rejects it.
pub fn accepts(filters: &[StdFilter], id: u16) -> Option<Fifo> {
    filters
        .iter()
        .find(|f| f.id1 == id || f.id2 == id)
        .map(|f| f.fifo)
}

/// Counters of [`RxPath`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RxCounts {
    /// Frames the filters rejected.
    pub rejected: u32,
    /// Frames lost because a hardware FIFO was full (IR.RF0L/RF1L).
    pub lost_fifo: u32,
    /// Frames lost because the RAM ring was full.
    pub lost_ring: u32,
    /// Most frames in the ring at once.
    pub ring_peak: u32,
}

/// The receive path: filters → two hardware FIFOs → (interrupt) → a ring
/// of `RING` frames the main loop reads. Frames are identifiers only.
#[derive(Debug, Clone)]
pub struct RxPath<const RING: usize> {
    filters: Vec<StdFilter, MAX_STD_FILTERS>,
    /// No filters: everything goes to FIFO 0 (the firmware before item 3).
    accept_all: bool,
    f0: Deque<u16, HW_FIFO>,
    f1: Deque<u16, HW_FIFO>,
    ring: Deque<u16, RING>,
    counts: RxCounts,
}

impl<const RING: usize> RxPath<RING> {
    /// A path with the filters of `set`, or accepting every frame into FIFO
    /// 0 when `set` is `None`.
    pub fn new(set: Option<&RxSet>) -> Self {
        Self {
            filters: set.and_then(|s| filters(s).ok()).unwrap_or_default(),
            accept_all: set.is_none(),
            f0: Deque::new(),
            f1: Deque::new(),
            ring: Deque::new(),
            counts: RxCounts::default(),
        }
    }

    /// A frame with identifier `id` completes on the bus; `isr` = the
    /// FDCAN interrupt can run now (it moves both FIFOs into the ring).
    pub fn frame(&mut self, id: u16, isr: bool) {
        let fifo = if self.accept_all {
            Some(Fifo::F0)
        } else {
            accepts(&self.filters, id)
        };
        let q = match fifo {
            None => {
                self.counts.rejected += 1;
                return;
            }
            Some(Fifo::F0) => &mut self.f0,
            Some(Fifo::F1) => &mut self.f1,
        };
        if q.push_back(id).is_err() {
            self.counts.lost_fifo += 1;
        }
        if isr {
            self.interrupt();
        }
    }

    /// The interrupt: FIFO 0 first, then FIFO 1, into the ring.
    pub fn interrupt(&mut self) {
        while let Some(id) = self.f0.pop_front().or_else(|| self.f1.pop_front()) {
            if self.ring.push_back(id).is_err() {
                self.counts.lost_ring += 1;
            }
        }
        self.counts.ring_peak = self.counts.ring_peak.max(self.ring.len() as u32);
    }

    /// The main loop takes the oldest frame (without the interrupt model:
    /// straight from the FIFOs, as the firmware before item 3 did).
    pub fn take(&mut self) -> Option<u16> {
        self.ring
            .pop_front()
            .or_else(|| self.f0.pop_front())
            .or_else(|| self.f1.pop_front())
    }

    /// The counters.
    pub fn counts(&self) -> RxCounts {
        self.counts
    }
}

impl RxSet {
    /// What `dev` listens to now: its node-id, SYNC COB-ID (0x1005), the
    /// valid RPDO COB-IDs (0x1400.. sub 1), the heartbeat consumers (0x1016)
    /// and LSS.
    pub fn from_device(dev: &perpend_can::Device) -> Self {
        let mut s = RxSet {
            node_id: dev.node_id(),
            sync: dev
                .read_u32(0x1005, 0)
                .map_or(0x080, |v| (v & 0x7FF) as u16),
            lss: true,
            ..RxSet::default()
        };
        for (k, slot) in s.rpdos.iter_mut().enumerate() {
            *slot = dev
                .read_u32(0x1400 + k as u16, 1)
                .filter(|v| v & 0x8000_0000 == 0)
                .map(|v| (v & 0x7FF) as u16);
        }
        for (k, slot) in s.heartbeats.iter_mut().enumerate() {
            *slot = dev
                .read_u32(0x1016, k as u8 + 1)
                .filter(|v| v & 0xFFFF != 0)
                .map(|v| (v >> 16) as u8);
        }
        s
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "rxfilter_tests.rs"]
mod tests;

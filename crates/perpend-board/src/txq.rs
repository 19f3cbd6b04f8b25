//! The software transmit queue between the application and the CAN
//! controller: the acquisition path never waits for the bus.
//!
//! The application pushes every frame it produces into a [`TxQueue`]
//! ([`TxQueue::push`] never blocks); [`TxQueue::service`] then offers the
//! queued frames, highest priority first, to the controller through the
//! small [`TxController`] trait and stops at the first frame it cannot take.
//! Nothing waits: a node alone on the bus (no acknowledge, so the
//! controller's transmit slots never free) only fills the queue.
//!
//! * **Order**: CAN priority, i.e. the lowest identifier first; frames with
//!   the same identifier leave in the order they were pushed (an EMCY and
//!   its "error reset", consecutive TPDOs). Keeping same-identifier frames in
//!   order *inside* the controller is the controller's part of the contract
//!   (the STM32 FDCAN transmits equal identifiers by buffer index, so the
//!   firmware's controller holds a frame back while one with its identifier
//!   is pending).
//! * **Displacement**: a controller may take a frame by giving back a
//!   pending lower-priority one ([`TryWrite::Displaced`]); that frame goes
//!   back into the queue ahead of the frames with its identifier (it is
//!   older than they are) and is sent later. It is never dropped silently.
//! * **Full queue**: the lowest-priority frame is dropped (the newest one
//!   among equal identifiers), so the queue always holds the
//!   highest-priority frames produced; every dropped frame is counted in
//!   [`TxStats::dropped`], which the application reports (object 0x2008,
//!   EMCY 0x8110, see `crate::app`).
//!
//! Limits: `N` frames (the firmware and the virtual board use
//! [`TX_QUEUE_LEN`]); counters wrap after 2³² frames.

use heapless::Vec;
use perpend_can::Frame;

/// Queue length of the firmware and the virtual board [frames]: two SYNC
/// periods' worth of TPDOs plus heartbeat, EMCYs and an SDO answer, eight
/// times over.
pub const TX_QUEUE_LEN: usize = 32;

/// What a controller did with a frame offered to it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TryWrite {
    /// The frame is in a transmit slot.
    Accepted,
    /// No slot can take the frame now; it stays queued.
    Full,
    /// The frame is in a transmit slot that held this pending
    /// lower-priority frame, which the controller took back (not sent).
    Displaced(Frame),
}

/// A CAN controller's transmit side, as the queue sees it.
pub trait TxController {
    /// Offers `f` for transmission without waiting. A controller must keep
    /// frames with the same identifier in the order they were accepted.
    fn try_write(&mut self, f: &Frame) -> TryWrite;
}

/// Counters of a [`TxQueue`] since it was created.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct TxStats {
    /// Frames dropped because the queue was full.
    pub dropped: u32,
    /// Frames the controller gave back and the queue took again.
    pub displaced: u32,
    /// Largest number of frames queued at once.
    pub peak: u16,
}

/// A transmit queue of at most `N` frames (see the module docs).
#[derive(Debug, Clone, Default)]
pub struct TxQueue<const N: usize> {
    frames: Vec<Frame, N>,
    stats: TxStats,
}

impl<const N: usize> TxQueue<N> {
    /// An empty queue.
    pub const fn new() -> Self {
        Self {
            frames: Vec::new(),
            stats: TxStats {
                dropped: 0,
                displaced: 0,
                peak: 0,
            },
        }
    }

    /// Queues a frame behind those of higher or equal priority. On a full
    /// queue the lowest-priority frame (possibly `f`) is dropped and
    /// counted. Returns whether `f` was kept.
    pub fn push(&mut self, f: Frame) -> bool {
        let pos = self.frames.partition_point(|q| q.id <= f.id);
        self.insert(pos, f)
    }

    /// Puts back a frame the controller displaced or gave back (a bit-rate
    /// switch): ahead of every queued frame with its identifier (they were
    /// pushed after it); counted in [`TxStats::displaced`].
    pub fn requeue(&mut self, f: Frame) -> bool {
        let pos = self.frames.partition_point(|q| q.id < f.id);
        self.stats.displaced = self.stats.displaced.wrapping_add(1);
        self.insert(pos, f)
    }

    fn insert(&mut self, pos: usize, f: Frame) -> bool {
        if self.frames.is_full() {
            self.stats.dropped = self.stats.dropped.wrapping_add(1);
            if pos >= self.frames.len() {
                return false;
            }
            self.frames.pop();
        }
        let kept = self.frames.insert(pos, f).is_ok();
        self.stats.peak = self.stats.peak.max(self.frames.len() as u16);
        kept
    }

    /// Offers the queued frames to `ctrl`, highest priority first, until it
    /// takes no more or the queue is empty; never waits. Returns the number
    /// of frames the controller took. A controller that keeps displacing
    /// frames is offered at most `2·N + 8` frames per call.
    pub fn service(&mut self, ctrl: &mut impl TxController) -> usize {
        let mut taken = 0;
        for _ in 0..2 * N + 8 {
            let Some(head) = self.frames.first().copied() else {
                break;
            };
            match ctrl.try_write(&head) {
                TryWrite::Full => break,
                TryWrite::Accepted => {
                    self.frames.remove(0);
                    taken += 1;
                }
                TryWrite::Displaced(back) => {
                    self.frames.remove(0);
                    taken += 1;
                    self.requeue(back);
                }
            }
        }
        taken
    }

    /// Number of frames queued.
    pub fn len(&self) -> usize {
        self.frames.len()
    }

    /// Whether nothing is queued.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// The queued frames in transmission order.
    pub fn frames(&self) -> &[Frame] {
        &self.frames
    }

    /// The counters.
    pub fn stats(&self) -> TxStats {
        self.stats
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "txq_tests.rs"]
mod tests;

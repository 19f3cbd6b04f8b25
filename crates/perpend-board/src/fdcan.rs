//! The FDCAN transmit-buffer logic of the firmware (Tx queue mode, three
//! buffers) and the run-time bit-rate switch, over a small trait of the
//! controller registers ([`FdcanRegs`]) so that the host tests it against a
//! fake controller that can misbehave.
//!
//! ## Transmission ([`FdcanTx`], a [`TxController`])
//!
//! * a frame is written only when TXFQS.TFQF says a buffer is free;
//! * when the three buffers are full, the cancellation of the pending frame
//!   with the numerically highest identifier is requested (TXBCR, RM0440
//!   §44.4.29) if it is above the new frame's, and "full" is returned; a
//!   later call sees the cancellation finished (TXBCF, §44.4.31): if the
//!   frame went out anyway (TXBTO, §44.4.30) nothing is given back,
//!   otherwise the new frame takes the buffer and the cancelled one (read
//!   back from the message RAM, §44.3.3) goes back to the queue as
//!   [`TryWrite::Displaced`];
//! * the queue mode sends equal identifiers by buffer index, so a frame is
//!   held back while one with its identifier is pending.
//!
//! ## Bit-rate switch ([`FdcanTx::switch_bitrate`], LSS "activate bit timing")
//!
//! Setting CCCR.CCE resets TXBRP, TXBTO, TXBCF and TXFQS (RM0440 §44.3.2,
//! the M_CAN core). A cancellation requested before the switch then never
//! reports TXBCF: the old firmware waited for it forever and every later
//! write returned "full" (no heartbeat, SDO or TPDO until reset). The switch
//! therefore: empties the receive FIFOs into the RAM ring, sets INIT (no
//! frame starts after it), reads the pending buffers back (TXBRP and the
//! message RAM, still intact under INIT) and the frame of an outstanding
//! cancellation that was not sent, forgets the cancellation, counts the
//! frames still in the receive FIFOs (lost: the ring was full), then sets
//! CCE, writes NBTP and leaves INIT. The frames read back are handed to
//! the caller, which puts them back into the software queue.
//!
//! Limits: classic CAN, 11-bit identifiers; a frame whose transmission
//! completed while INIT was being set is read back as not sent only if
//! TXBRP still showed it, so at most a duplicate, never a loss.

use heapless::Vec;
use perpend_can::Frame;

use crate::txq::{TryWrite, TxController};

/// Tx buffers of the G4 FDCAN (message RAM, RM0440 §44.3.3).
pub const BUFFERS: usize = 3;

/// The FDCAN registers the transmit logic and the bit-rate switch use
/// (bit `k` of a mask = Tx buffer `k`).
pub trait FdcanRegs {
    /// TXBRP: buffers with a transmission request pending.
    fn pending(&mut self) -> u32;
    /// TXBCF: buffers whose cancellation finished.
    fn cancel_finished(&mut self) -> u32;
    /// TXBTO: buffers whose transmission occurred.
    fn transmitted(&mut self) -> u32;
    /// TXFQS.TFQF: no buffer is free.
    fn queue_full(&mut self) -> bool;
    /// The frame held by buffer `k` (message RAM).
    fn buffer(&mut self, k: usize) -> Frame;
    /// TXBCR: requests the cancellation of buffer `k`.
    fn request_cancel(&mut self, k: usize);
    /// TXBAR: requests the transmission of buffer `k` again.
    fn add_request(&mut self, k: usize);
    /// Writes `f` into a free buffer (called only when one is free);
    /// `false` if the controller did not take it.
    fn write(&mut self, f: &Frame) -> bool;
    /// Moves the frames waiting in the receive FIFOs into the RAM ring.
    fn drain_rx(&mut self);
    /// Frames left in both receive FIFOs (RXF0S.F0FL + RXF1S.F1FL).
    fn rx_fill(&mut self) -> u32;
    /// Sets CCCR.INIT and waits until it reads back.
    fn enter_init(&mut self);
    /// Sets CCCR.CCE (which resets TXBRP/TXBTO/TXBCF/TXFQS), writes NBTP,
    /// clears CCE and INIT and waits until INIT reads 0.
    fn program_nbtp(&mut self, nbtp: u32);
}

/// What a bit-rate switch did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Switched {
    /// Frames read back from the transmit buffers, not sent: to be put
    /// back into the software queue.
    pub requeue: Vec<Frame, BUFFERS>,
    /// Received frames lost (still in the FIFOs after draining them).
    pub rx_lost: u32,
}

/// The FDCAN transmit side (see the module docs).
#[derive(Debug)]
pub struct FdcanTx<R> {
    regs: R,
    /// Buffer whose cancellation was requested, and the frame it held.
    cancelling: Option<(usize, Frame)>,
}

impl<R: FdcanRegs> FdcanTx<R> {
    /// The logic over `regs`.
    pub const fn new(regs: R) -> Self {
        Self {
            regs,
            cancelling: None,
        }
    }

    /// The registers.
    pub fn regs_mut(&mut self) -> &mut R {
        &mut self.regs
    }

    /// Whether a cancellation is outstanding.
    pub fn is_cancelling(&self) -> bool {
        self.cancelling.is_some()
    }

    fn pending_frames(&mut self) -> impl Iterator<Item = (usize, Frame)> + '_ {
        let mask = self.regs.pending();
        (0..BUFFERS)
            .filter(move |k| mask & (1 << k) != 0)
            .map(|k| (k, self.regs.buffer(k)))
    }

    /// Resolves a requested cancellation: `Err(())` while it runs,
    /// `Ok(Some((k, frame)))` when buffer `k` was cancelled (free, its
    /// frame not sent), `Ok(None)` otherwise.
    fn resolve_cancel(&mut self) -> Result<Option<(usize, Frame)>, ()> {
        let Some((k, f)) = self.cancelling else {
            return Ok(None);
        };
        if self.regs.cancel_finished() & (1 << k) == 0 {
            return Err(());
        }
        self.cancelling = None;
        let sent = self.regs.transmitted() & (1 << k) != 0;
        Ok((!sent).then_some((k, f)))
    }

    /// Requests the cancellation of the lowest-priority pending frame if
    /// its identifier is above `id` (all buffers are pending).
    fn request_cancel(&mut self, id: u16) {
        let worst = self.pending_frames().max_by_key(|(_, f)| f.id);
        if let Some((k, f)) = worst.filter(|(_, f)| f.id > id) {
            self.regs.request_cancel(k);
            self.cancelling = Some((k, f));
        }
    }

    /// Switches the nominal bit timing to `nbtp` (see the module docs):
    /// returns the frames to requeue and the received frames lost.
    pub fn switch_bitrate(&mut self, nbtp: u32) -> Switched {
        let mut out = Switched::default();
        self.regs.drain_rx();
        self.regs.enter_init();
        let mask = self.regs.pending();
        for (_, f) in self.pending_frames() {
            // At most BUFFERS frames: cannot fail.
            let _ = out.requeue.push(f);
        }
        if let Some((k, f)) = self.cancelling.take() {
            let done = self.regs.cancel_finished() & (1 << k) != 0;
            let sent = self.regs.transmitted() & (1 << k) != 0;
            if mask & (1 << k) == 0 && done && !sent {
                let _ = out.requeue.push(f);
            }
        }
        self.regs.drain_rx();
        out.rx_lost = self.regs.rx_fill();
        self.regs.program_nbtp(nbtp);
        out
    }
}

impl<R: FdcanRegs> TxController for FdcanTx<R> {
    fn try_write(&mut self, f: &Frame) -> TryWrite {
        let Ok(cancelled) = self.resolve_cancel() else {
            return TryWrite::Full;
        };
        let same_id = self.pending_frames().any(|(_, p)| p.id == f.id);
        if same_id {
            if let Some((k, _)) = cancelled {
                // The cancelled frame was not sent: request it again (its
                // buffer is untouched).
                self.regs.add_request(k);
            }
            return TryWrite::Full;
        }
        if self.regs.queue_full() {
            self.request_cancel(f.id);
            return TryWrite::Full;
        }
        if self.regs.write(f) {
            return match cancelled {
                Some((_, back)) => TryWrite::Displaced(back),
                None => TryWrite::Accepted,
            };
        }
        // Not reached (a buffer was free); never lose the cancelled frame.
        if let Some((k, _)) = cancelled {
            self.regs.add_request(k);
        }
        TryWrite::Full
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "fdcan_tests.rs"]
mod tests;

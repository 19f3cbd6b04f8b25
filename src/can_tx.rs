//! The FDCAN1 transmit side as a [`TxController`] of the board's software
//! queue ([`perpend_board::txq`]): offering a frame never waits.
//!
//! The controller runs in Tx **queue** mode (TXBC.TFQM = 1, RM0440
//! §44.3.6 "Tx queue"): its three Tx buffers are sent lowest identifier
//! first. What this module adds to embassy-stm32 0.6:
//!
//! * **No waiting.** `CanTx::write` is async: it waits while no buffer is
//!   free. It is polled exactly once (`embassy_futures::poll_once`), and
//!   only when TXFQS.TFQF says a buffer is free, so it completes at once.
//! * **Displacement with the right comparison.** When all three buffers are
//!   full, embassy's `Registers::write` aborts the first buffer whose frame
//!   compares `new_id > pending_id` with `embedded_can::Id`'s `Ord` — whose
//!   "smaller" is the *more* dominant identifier — so it throws out a
//!   pending frame of **higher** priority than the new one (and busy-waits
//!   for the abort). It is never reached here: when the buffers are full
//!   this module requests the cancellation of the pending frame with the
//!   numerically highest identifier, if that is above the new frame's
//!   (TXBCR, §44.4.29), and returns "full"; a later call sees the
//!   cancellation finished (TXBCF, §44.4.31): if the frame went out anyway
//!   (TXBTO, §44.4.30) nothing is returned, otherwise the new frame takes
//!   the buffer and the cancelled one (read back from the message RAM,
//!   §44.3.3) goes back to the queue as `Displaced`.
//! * **Order among equal identifiers.** The queue mode sends equal
//!   identifiers by buffer index, not in write order; a frame is therefore
//!   held back while one with its identifier is pending (an EMCY and its
//!   "error reset", consecutive TPDOs keep their order).
//!
//! Limits: classic CAN, 11-bit identifiers only; untested on silicon.

use core::task::Poll;

use embassy_futures::poll_once;
use embassy_stm32::can::{self, CanTx};
use embassy_stm32::pac;
use perpend_board::txq::{TryWrite, TxController};
use perpend_can::Frame;

/// Tx buffers of the G4 FDCAN (message RAM, RM0440 §44.3.3).
const BUFFERS: usize = 3;
/// Words per Tx buffer element in the G4 message RAM (T0, T1, 64 data
/// bytes).
const ELEMENT_WORDS: usize = 18;

/// A perpend frame as the HAL's frame (`None`: not a valid classic frame).
pub fn to_hal(f: &Frame) -> Option<can::frame::Frame> {
    if f.rtr {
        can::frame::Frame::new_remote(embedded_can::StandardId::new(f.id)?, f.len as usize).ok()
    } else {
        can::frame::Frame::new_standard(f.id, f.payload()).ok()
    }
}

/// A HAL frame as a perpend frame (`None` for extended identifiers, which
/// are not CANopen classic).
pub fn from_hal(f: &can::frame::Frame) -> Option<Frame> {
    let embedded_can::Id::Standard(id) = f.id() else {
        return None;
    };
    let mut out = Frame::new(id.as_raw(), f.data());
    if f.header().rtr() {
        out = Frame::remote(id.as_raw(), f.header().len());
    }
    Some(out)
}

/// Whether Tx buffer `k` has a transmission request pending (TXBRP).
fn pending(k: usize) -> bool {
    pac::FDCAN1.txbrp().read().trp(k)
}

/// The frame held by Tx buffer `k`, read back from the message RAM: T0
/// (ID\[28:18\], RTR bit 29), T1 (DLC\[19:16\]), data words 2 and 3.
fn buffer_frame(k: usize) -> Frame {
    let word = |w: usize| pac::FDCANRAM1.txbuf(k * ELEMENT_WORDS + w).read();
    let (t0, t1) = (word(0), word(1));
    let id = ((t0 >> 18) & 0x7FF) as u16;
    let len = (((t1 >> 16) & 0xF) as u8).min(8);
    if t0 & (1 << 29) != 0 {
        return Frame::remote(id, len);
    }
    let mut data = [0u8; 8];
    data[..4].copy_from_slice(&word(2).to_le_bytes());
    data[4..].copy_from_slice(&word(3).to_le_bytes());
    Frame::new(id, &data[..len as usize])
}

/// The FDCAN transmit side (see the module docs).
pub struct FdcanTx<'d> {
    tx: CanTx<'d>,
    /// Buffer whose cancellation was requested, and the frame it held.
    cancelling: Option<(usize, Frame)>,
}

impl<'d> FdcanTx<'d> {
    /// Wraps the driver's transmit half.
    pub fn new(tx: CanTx<'d>) -> Self {
        Self {
            tx,
            cancelling: None,
        }
    }

    /// Resolves a requested cancellation: `Err(())` while it runs,
    /// `Ok(Some((k, frame)))` when buffer `k` was cancelled (free, its
    /// frame not sent), `Ok(None)` otherwise.
    fn resolve_cancel(&mut self) -> Result<Option<(usize, Frame)>, ()> {
        let Some((k, f)) = self.cancelling else {
            return Ok(None);
        };
        if !pac::FDCAN1.txbcf().read().cf(k) {
            return Err(());
        }
        self.cancelling = None;
        let sent = pac::FDCAN1.txbto().read().to(k);
        Ok((!sent).then_some((k, f)))
    }

    /// Requests the cancellation of the lowest-priority pending frame if
    /// its identifier is above `id` (all buffers are pending).
    fn request_cancel(&mut self, id: u16) {
        let worst = (0..BUFFERS)
            .filter(|&k| pending(k))
            .map(|k| (k, buffer_frame(k)))
            .max_by_key(|(_, f)| f.id);
        if let Some((k, f)) = worst.filter(|(_, f)| f.id > id) {
            pac::FDCAN1.txbcr().write(|w| w.set_cr(k, true));
            self.cancelling = Some((k, f));
        }
    }
}

impl TxController for FdcanTx<'_> {
    fn try_write(&mut self, f: &Frame) -> TryWrite {
        let Some(hal) = to_hal(f) else {
            defmt::warn!("frame {=u16:#x} is not a classic CAN frame: not sent", f.id);
            return TryWrite::Accepted;
        };
        let Ok(cancelled) = self.resolve_cancel() else {
            return TryWrite::Full;
        };
        let same_id = (0..BUFFERS).any(|k| pending(k) && buffer_frame(k).id == f.id);
        if same_id {
            if let Some((k, _)) = cancelled {
                // The cancelled frame was not sent: request it again (its
                // buffer is untouched).
                pac::FDCAN1.txbar().write(|w| w.set_ar(k, true));
            }
            return TryWrite::Full;
        }
        if pac::FDCAN1.txfqs().read().tfqf() {
            self.request_cancel(f.id);
            return TryWrite::Full;
        }
        // A buffer is free: the driver writes it without waiting or
        // displacing anything.
        match poll_once(self.tx.write(&hal)) {
            Poll::Ready(None) => match cancelled {
                Some((_, back)) => TryWrite::Displaced(back),
                None => TryWrite::Accepted,
            },
            Poll::Ready(Some(d)) => match from_hal(&d) {
                Some(d) => TryWrite::Displaced(d),
                None => TryWrite::Accepted,
            },
            Poll::Pending => {
                // Not reached (a buffer was free); never lose the
                // cancelled frame.
                if let Some((k, _)) = cancelled {
                    pac::FDCAN1.txbar().write(|w| w.set_ar(k, true));
                }
                TryWrite::Full
            }
        }
    }
}

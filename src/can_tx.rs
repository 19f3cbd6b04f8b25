//! The FDCAN1 transmit side as a [`TxController`] of the board's software
//! queue ([`perpend_board::txq`]): offering a frame never waits. The
//! decisions (cancellation, displacement, order, the bit-rate switch with a
//! cancellation outstanding) are `perpend_board::fdcan`'s, tested on the
//! host against a fake controller; this module is its register access
//! ([`Fdcan1`]).
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
use perpend_board::fdcan::FdcanRegs;
use perpend_can::Frame;

use crate::can_rx::from_hal;
use perpend_core::params::Bitrate;

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

/// FDCAN1's registers for `perpend_board::fdcan`, and the driver's
/// transmit half for writing a free buffer.
pub struct Fdcan1<'d> {
    tx: CanTx<'d>,
}

/// The FDCAN1 transmit side (see the module docs).
pub type FdcanTx<'d> = perpend_board::fdcan::FdcanTx<Fdcan1<'d>>;

/// Wraps the driver's transmit half.
pub fn new(tx: CanTx<'_>) -> FdcanTx<'_> {
    FdcanTx::new(Fdcan1 { tx })
}

impl FdcanRegs for Fdcan1<'_> {
    fn pending(&mut self) -> u32 {
        pac::FDCAN1.txbrp().read().0
    }
    fn cancel_finished(&mut self) -> u32 {
        pac::FDCAN1.txbcf().read().0
    }
    fn transmitted(&mut self) -> u32 {
        pac::FDCAN1.txbto().read().0
    }
    fn queue_full(&mut self) -> bool {
        pac::FDCAN1.txfqs().read().tfqf()
    }
    fn buffer(&mut self, k: usize) -> Frame {
        buffer_frame(k)
    }
    fn request_cancel(&mut self, k: usize) {
        pac::FDCAN1.txbcr().write(|w| w.set_cr(k, true));
    }
    fn add_request(&mut self, k: usize) {
        pac::FDCAN1.txbar().write(|w| w.set_ar(k, true));
    }
    fn write(&mut self, f: &Frame) -> bool {
        let Some(hal) = to_hal(f) else {
            defmt::warn!("frame {=u16:#x} is not a classic CAN frame: not sent", f.id);
            // Dropped on purpose: taken, so the queue moves on.
            return true;
        };
        // A buffer is free: the driver writes it without waiting or
        // displacing anything (its displacement is never reached).
        match poll_once(self.tx.write(&hal)) {
            Poll::Ready(None) => true,
            Poll::Ready(Some(d)) => {
                defmt::warn!(
                    "frame {=u32:#x} displaced by the driver: lost",
                    from_hal(&d).map_or(0, |f| u32::from(f.id))
                );
                true
            }
            Poll::Pending => false,
        }
    }
    fn drain_rx(&mut self) {
        crate::can_rx::drain();
    }
    fn rx_fill(&mut self) -> u32 {
        crate::can_rx::fifo_fill()
    }
    fn enter_init(&mut self) {
        let r = pac::FDCAN1;
        r.cccr().modify(|w| w.set_init(true));
        while !r.cccr().read().init() {}
    }
    fn program_nbtp(&mut self, nbtp: u32) {
        // RM0440 §44.3.2: CCE with INIT set, NBTP, then INIT cleared (the
        // bus is re-joined after 11 recessive bits).
        let r = pac::FDCAN1;
        r.cccr().modify(|w| w.set_cce(true));
        r.nbtp().write_value(pac::can::regs::Nbtp(nbtp));
        r.cccr().modify(|w| {
            w.set_cce(false);
            w.set_init(false);
        });
        while r.cccr().read().init() {}
    }
}

/// The board's FDCAN nominal bit timing for `b` as the driver's type
/// (`None` only if the table held a value the type cannot).
pub fn nominal_timing(b: Bitrate) -> Option<can::config::NominalBitTiming> {
    let t = perpend_board::bittiming::for_board(b);
    Some(can::config::NominalBitTiming {
        prescaler: core::num::NonZeroU16::new(t.prescaler)?,
        seg1: core::num::NonZeroU8::new(u8::try_from(t.seg1).ok()?)?,
        seg2: core::num::NonZeroU8::new(t.seg2)?,
        sync_jump_width: core::num::NonZeroU8::new(t.sjw)?,
    })
}

/// The board's FDCAN configuration at `b` (the firmware's and the HIL
/// tests'): explicit bit timing, Tx queue mode (lowest identifier first),
/// and the global filter that rejects what no acceptance filter takes (set
/// before the filters).
pub fn configure(cc: &mut can::CanConfigurator<'_>, b: Bitrate) {
    match nominal_timing(b) {
        Some(nbt) => {
            let c = cc.config().set_nominal_bit_timing(nbt);
            cc.set_config(c.set_tx_buffer_mode(can::config::TxBufferMode::Priority));
        }
        None => cc.set_bitrate(b.bps()),
    }
    cc.set_config(crate::can_rx::with_global_filter(cc.config()));
    defmt::info!(
        "FDCAN NBTP {=u32:#010x}",
        perpend_board::bittiming::for_board(b).nbtp()
    );
}

//! A fake FDCAN transmit side for the tests of [`super::FdcanTx`] (host,
//! `fdcan_tests.rs`) and the same logic as compiled for the board
//! (`xtask/qemu-tests`, QEMU): the three Tx buffers, TXBRP/TXBCF/TXBTO, a
//! cancellation that can stay outstanding, and a CCE that resets the
//! transmit state as the M_CAN core does (RM0440 §44.4). no_std.

use super::{FdcanRegs, Frame, BUFFERS};

/// Three Tx buffers, TXBRP/TXBCF/TXBTO, the receive FIFOs and a RAM ring.
#[derive(Default)]
pub struct Fake {
    pub slots: [Option<Frame>; BUFFERS],
    pub brp: u32,
    pub bcf: u32,
    pub bto: u32,
    /// Cancellations requested, completed at the next bus tick unless
    /// `hold_cancel`.
    pub cancel_req: u32,
    pub hold_cancel: bool,
    pub init: bool,
    pub nbtp: u32,
    pub rx_fifo: u32,
    pub ring_room: u32,
    pub ring: u32,
    pub sent: heapless::Vec<Frame, 32>,
}

impl Fake {
    /// One frame time: cancellations complete, then the pending frame
    /// with the lowest identifier is sent (nothing under INIT).
    pub fn tick(&mut self) {
        if self.init {
            return;
        }
        if !self.hold_cancel {
            self.bcf |= self.cancel_req & self.brp;
            self.brp &= !self.cancel_req;
            self.cancel_req = 0;
        }
        let best = (0..BUFFERS)
            .filter(|k| self.brp & (1 << k) != 0)
            .min_by_key(|&k| self.slots[k].map(|f| f.id));
        if let Some(k) = best {
            self.brp &= !(1 << k);
            self.bto |= 1 << k;
            if let Some(f) = self.slots[k] {
                let _ = self.sent.push(f);
            }
        }
    }
}

impl FdcanRegs for Fake {
    fn pending(&mut self) -> u32 {
        self.brp
    }
    fn cancel_finished(&mut self) -> u32 {
        self.bcf
    }
    fn transmitted(&mut self) -> u32 {
        self.bto
    }
    fn queue_full(&mut self) -> bool {
        self.brp == (1 << BUFFERS) - 1
    }
    fn buffer(&mut self, k: usize) -> Frame {
        self.slots[k].unwrap_or_else(|| Frame::new(0x7FF, &[]))
    }
    fn request_cancel(&mut self, k: usize) {
        self.cancel_req |= 1 << k;
    }
    fn add_request(&mut self, k: usize) {
        self.brp |= 1 << k;
        self.bcf &= !(1 << k);
        self.bto &= !(1 << k);
    }
    fn write(&mut self, f: &Frame) -> bool {
        let Some(k) = (0..BUFFERS).find(|k| self.brp & (1 << k) == 0) else {
            return false;
        };
        self.slots[k] = Some(*f);
        self.add_request(k);
        true
    }
    fn drain_rx(&mut self) {
        let n = self.rx_fifo.min(self.ring_room - self.ring);
        self.rx_fifo -= n;
        self.ring += n;
    }
    fn rx_fill(&mut self) -> u32 {
        self.rx_fifo
    }
    fn enter_init(&mut self) {
        self.init = true;
    }
    fn program_nbtp(&mut self, nbtp: u32) {
        assert!(self.init, "NBTP written outside INIT");
        // CCE: the M_CAN core resets the transmit state (the message RAM
        // keeps its contents); requested cancellations are forgotten.
        self.brp = 0;
        self.bcf = 0;
        self.bto = 0;
        self.cancel_req = 0;
        self.nbtp = nbtp;
        self.init = false;
    }
}

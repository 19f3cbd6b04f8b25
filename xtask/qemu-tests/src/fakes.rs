//! Fakes of the FDCAN transmit registers and of the flash ECC registers
//! for the target tests (the models of RM0440 §44.4 and §3.7.7 that the
//! host tests of perpend-board use, in no_std form).

use heapless::Vec;
use perpend_board::ecc::{EccFlags, EccRegs, MAX_FAULTS};
use perpend_board::fdcan::{FdcanRegs, BUFFERS};
use perpend_board::storage::WORD;
use perpend_can::Frame;

/// Three Tx buffers with TXBRP/TXBCF/TXBTO, the receive FIFOs (`rx`
/// frames) and a CCE that resets the transmit state as the M_CAN core.
#[derive(Default)]
pub struct FakeFdcan {
    slots: [Option<Frame>; BUFFERS],
    brp: u32,
    bcf: u32,
    bto: u32,
    cancel_req: u32,
    /// Cancellations stay outstanding.
    pub hold_cancel: bool,
    init: bool,
    /// Last NBTP programmed.
    pub nbtp: u32,
    /// Frames in the receive FIFOs.
    pub rx: u32,
    /// Frames sent, in order.
    pub sent: Vec<Frame, 16>,
}

impl FakeFdcan {
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

impl FdcanRegs for FakeFdcan {
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
        self.rx = 0;
    }
    fn rx_fill(&mut self) -> u32 {
        self.rx
    }
    fn enter_init(&mut self) {
        self.init = true;
    }
    fn program_nbtp(&mut self, nbtp: u32) {
        // CCCR.CCE resets TXBRP/TXBTO/TXBCF/TXFQS (RM0440 §44.4).
        self.brp = 0;
        self.bcf = 0;
        self.bto = 0;
        self.cancel_req = 0;
        self.nbtp = nbtp;
        self.init = false;
    }
}

/// Flash ECC: one double word with a single error, up to two with a
/// double error; ECCC/ECCD set only when both were clear (RM0440 §3.7.7),
/// the NMI records double-error offsets.
pub struct FakeEcc {
    /// Offset of the double word with a single error.
    pub single_at: Option<u32>,
    /// Offsets of the double words with a double error.
    pub double_at: [Option<u32>; 2],
    flags: EccFlags,
    /// ACR.DCEN.
    pub dcache_on: bool,
    faults: Vec<u32, MAX_FAULTS>,
}

impl Default for FakeEcc {
    fn default() -> Self {
        Self {
            single_at: None,
            double_at: [None; 2],
            flags: EccFlags::default(),
            dcache_on: true,
            faults: Vec::new(),
        }
    }
}

impl EccRegs for FakeEcc {
    fn flags(&mut self) -> EccFlags {
        self.flags
    }
    fn clear_flags(&mut self) {
        self.flags = EccFlags::default();
    }
    fn dcache_enabled(&mut self) -> bool {
        self.dcache_on
    }
    fn set_dcache(&mut self, on: bool) {
        self.dcache_on = on;
    }
    fn reset_dcache(&mut self) {}
    fn load(&mut self, offset: u32, bytes: &mut [u8]) {
        bytes.fill(0x5A);
        let word = offset - offset % WORD as u32;
        let armed = self.flags == EccFlags::default();
        if Some(word) == self.single_at && armed {
            self.flags.corrected = true;
        }
        if self.double_at.contains(&Some(word)) {
            if armed {
                self.flags.detected = true;
            }
            let _ = self.faults.push(word);
        }
    }
    fn take_faults(&mut self) -> Option<Vec<u32, MAX_FAULTS>> {
        Some(core::mem::take(&mut self.faults))
    }
}

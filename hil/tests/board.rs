//! On-target tests of the board (issue 33 item 3), run by `cargo xtask
//! hil` with `probe-rs run` on a NUCLEO-G474RE: embedded-test resets the
//! part before each test and runs it alone.
//!
//! * FDCAN1 in internal loopback (CCCR.TEST, TEST.LBCK, CCCR.MON, RM0440
//!   §44.3.2: no transceiver, the controller acknowledges its own frames)
//!   through the firmware's `can_tx`/`can_rx` and `perpend_board::fdcan`:
//!   send/receive, acceptance filters, TX cancellation, the bit-rate switch
//!   with a cancellation outstanding. Transmission is held back with the
//!   restricted operation mode (CCCR.ASM: the node receives and
//!   acknowledges but does not send), so all three Tx buffers can be kept
//!   pending.
//! * ADC1 on TIM3's TRGO with the firmware's `acq_ctl`: scan period and the
//!   reconfiguration sequence (period and oversampling changed, CFGR2
//!   read back).
//! * Flash: store and restore in the firmware's storage pages, the store
//!   cut at each flash operation (the n-th operation refused; the torn
//!   word of a real power cut is modelled on the host by `FaultFlash`).
//! * ECC: the STM32G4 has no way to inject an ECC error by software (no
//!   test register; programming a non-erased double word is refused with
//!   PROGERR, RM0440 §3.3.7): only the clean path is tested on the part —
//!   a read of the storage pages reports no error and leaves ECCC/ECCD
//!   clear (double-error detection armed). The double-error path is tested
//!   on the host and under QEMU (`cargo xtask hil --qemu`).
//! * Reset cause (RCC_CSR), the IWDG (period from PR/RLR, kept alive by
//!   petting), the stack guard (an overflow faults).
//!
//! The IWDG cannot be stopped once started: its test runs last.

#![no_std]
#![no_main]
// A test binary: a failed assertion or `panic!` is the test's failure.
#![allow(clippy::panic, clippy::unwrap_used)]

use core::sync::atomic::{AtomicBool, Ordering};

use embassy_stm32::{bind_interrupts, can, dma, pac, peripherals, Peripherals};
use perpend_board::rxfilter::{self, RxSet};
use perpend_board::txq::TxQueue;
use perpend_can::Frame;
use perpend_core::params::Bitrate;
use perpend_hil::{can_rx, can_tx};

bind_interrupts!(struct Irqs {
    FDCAN1_IT0 => can::IT0InterruptHandler<peripherals::FDCAN1>, can_rx::RxInterrupt;
    FDCAN1_IT1 => can::IT1InterruptHandler<peripherals::FDCAN1>;
    DMA1_CHANNEL1 => dma::InterruptHandler<peripherals::DMA1_CH1>;
});

/// The stack-guard test expects a fault: the fault handlers then report
/// success instead of failure.
static EXPECT_FAULT: AtomicBool = AtomicBool::new(false);

/// Ends the test from a fault handler: passed if a fault was expected.
fn fault_exit() -> ! {
    if EXPECT_FAULT.load(Ordering::SeqCst) {
        embedded_test::export::hosting::exit(0)
    } else {
        embedded_test::export::hosting::abort()
    }
}

#[cortex_m_rt::exception]
unsafe fn MemoryManagement() {
    fault_exit()
}

#[cortex_m_rt::exception]
unsafe fn HardFault(_: &cortex_m_rt::ExceptionFrame) -> ! {
    fault_exit()
}

/// The node's receive set (node 0x20, SYNC 0x80, LSS).
fn rx_set() -> RxSet {
    RxSet {
        node_id: 0x20,
        sync: 0x80,
        rpdos: [None; rxfilter::MAX_RPDOS],
        heartbeats: [None; rxfilter::MAX_HEARTBEATS],
        lss: true,
    }
}

/// FDCAN1 as the firmware configures it at `b`, in internal loopback, the
/// node's acceptance filters programmed, the receiver in the firmware's
/// ring.
fn loopback(p: Peripherals, b: Bitrate) -> can_tx::FdcanTx<'static> {
    let mut cc = can::CanConfigurator::new(p.FDCAN1, p.PA11, p.PA12, Irqs);
    can_tx::configure(&mut cc, b);
    let (tx, rx, props) = cc.into_internal_loopback_mode().split();
    if let Ok(f) = rxfilter::filters(&rx_set()) {
        can_rx::program(&props, &f);
    }
    can_rx::install(rx);
    can_tx::new(tx)
}

/// Restricted operation (CCCR.ASM) on or off: on, nothing is sent.
fn restricted(on: bool) {
    let r = pac::FDCAN1;
    if on {
        r.cccr().modify(|w| w.set_init(true));
        while !r.cccr().read().init() {}
        r.cccr().modify(|w| w.set_cce(true));
        r.cccr().modify(|w| w.set_asm(true));
        r.cccr().modify(|w| {
            w.set_cce(false);
            w.set_init(false);
        });
        while r.cccr().read().init() {}
    } else {
        r.cccr().modify(|w| w.set_asm(false));
    }
}

/// FDCAN1 in loopback, restricted: 0x181..0x183 fill the three Tx buffers,
/// 0x0A0 (more urgent) waits in the queue.
fn three_pending(p: Peripherals) -> (can_tx::FdcanTx<'static>, TxQueue<8>) {
    let mut tx = loopback(p, Bitrate::M1);
    restricted(true);
    let mut q = TxQueue::<8>::new();
    for id in [0x181, 0x182, 0x183] {
        q.push(Frame::new(id, &[2]));
    }
    q.service(&mut tx);
    assert_eq!(pac::FDCAN1.txbrp().read().0 & 0b111, 0b111);
    q.push(Frame::new(0x0A0, &[3]));
    (tx, q)
}

/// The next received frame within 100 ms.
async fn received() -> Option<Frame> {
    let t = embassy_time::Duration::from_millis(100);
    embassy_time::with_timeout(t, can_rx::next()).await.ok()
}

#[embedded_test::tests]
mod tests {
    use super::*;
    use perpend_board::storage::{load, save, Boot, EccGuard, SeqStore};
    use perpend_core::params::Params;
    use perpend_hil::{acq_ctl, board, flash};

    #[init]
    fn init() -> Peripherals {
        let p = embassy_stm32::init(board::config());
        board::freeze_iwdg_in_debug();
        p
    }

    /// A frame to this node's SDO server comes back through the filters
    /// and the firmware's receive ring, unchanged.
    #[test]
    async fn fdcan_loopback_send_receive(p: Peripherals) {
        let mut tx = loopback(p, Bitrate::M1);
        let mut q = TxQueue::<8>::new();
        let f = Frame::new(0x620, &[0x40, 0x00, 0x10, 0, 0, 0, 0, 0]);
        q.push(f);
        q.service(&mut tx);
        assert_eq!(received().await, Some(f));
    }

    /// A foreign SDO (node 0x21) is rejected by the acceptance filters; the
    /// node's own SDO and NMT pass.
    #[test]
    async fn fdcan_filters(p: Peripherals) {
        let mut tx = loopback(p, Bitrate::M1);
        let mut q = TxQueue::<8>::new();
        for f in [Frame::new(0x621, &[1]), Frame::new(0x000, &[1, 0x20])] {
            q.push(f);
        }
        q.service(&mut tx);
        assert_eq!(received().await.map(|f| f.id), Some(0x000));
        assert_eq!(received().await, None, "a rejected frame arrived");
    }

    /// All three buffers pending (restricted mode): a more urgent frame
    /// has the lowest-priority one cancelled and takes its buffer; the
    /// cancelled frame goes back to the queue; all four then arrive in
    /// identifier order.
    #[test]
    async fn fdcan_tx_cancellation(p: Peripherals) {
        let (mut tx, mut q) = three_pending(p);
        for _ in 0..4 {
            q.service(&mut tx);
        }
        assert_eq!(q.frames().first().map(|f| f.id), Some(0x183));
        restricted(false);
        q.service(&mut tx);
        for id in [0x0A0, 0x181, 0x182, 0x183] {
            let f = received().await;
            assert_eq!(f.map(|f| f.id), Some(id));
            q.service(&mut tx);
        }
    }

    /// Issue 33 defect 1 on the part: three frames pending, a cancellation
    /// requested, then the LSS bit-rate switch (CCE resets the transmit
    /// state): the frames are requeued, the cancellation is forgotten, NBTP
    /// holds the new timing and every frame arrives at the new rate.
    #[test]
    async fn fdcan_bitrate_switch_with_cancel_outstanding(p: Peripherals) {
        let (mut tx, mut q) = three_pending(p);
        q.service(&mut tx);
        let nbtp = perpend_board::bittiming::for_board(Bitrate::K250).nbtp();
        let sw = tx.switch_bitrate(nbtp);
        assert!(!tx.is_cancelling(), "cancellation outlived the switch");
        assert_eq!(sw.requeue.len(), 3);
        assert_eq!(pac::FDCAN1.nbtp().read().0, nbtp);
        for f in sw.requeue {
            q.requeue(f);
        }
        restricted(false);
        let mut got = 0;
        for _ in 0..4 {
            q.service(&mut tx);
            got += u32::from(received().await.is_some());
        }
        assert_eq!(got, 4, "frames lost across the switch");
    }

    /// ADC1 scans on TIM3 at the factory period, then after the
    /// firmware's reconfiguration sequence at twice the period with
    /// another oversampling ratio: 200 scans within 2 % of their time,
    /// CFGR2.OVSR as configured.
    #[test]
    async fn adc_scan_timing_and_reconfiguration(p: Peripherals) {
        let inputs = [
            embassy_stm32::adc::AdcChannel::degrade_adc(p.PA0),
            embassy_stm32::adc::AdcChannel::degrade_adc(p.PA1),
            embassy_stm32::adc::AdcChannel::degrade_adc(p.PB0),
            embassy_stm32::adc::AdcChannel::degrade_adc(p.PC1),
        ];
        let mut acq = Params::factory().acq;
        let (mut ring, _) = acq_ctl::start(p.ADC1, p.DMA1_CH1, inputs, &acq, Irqs);
        let tim = embassy_stm32::timer::low_level::Timer::new(p.TIM3);
        tim.set_master_mode(embassy_stm32::timer::low_level::MasterMode::UPDATE);
        for step in 0..2 {
            assert!(
                acq_ctl::restart(&mut ring, &tim, &acq, false),
                "ADC did not stop"
            );
            let mut scan = [0u16; acq_ctl::SCAN];
            let _ = ring.read(&mut scan).await;
            let t0 = embassy_time::Instant::now();
            for _ in 0..200 {
                assert!(ring.read(&mut scan).await.is_ok(), "DMA overrun");
            }
            let us = (embassy_time::Instant::now() - t0).as_micros() as f32;
            let want = 200.0 * acq.period_us as f32;
            assert!(
                (us - want).abs() <= 0.02 * want,
                "scan period off by more than 2 %"
            );
            let ovsr = pac::ADC1.cfgr2().read().ovsr();
            assert_eq!(ovsr, acq.os_log2.clamp(1, 8) - 1);
            if step == 0 {
                acq.period_us *= 2;
                acq.os_log2 = if acq.os_log2 == 4 { 2 } else { 4 };
            }
        }
    }

    /// Store and restore in the storage pages with the store cut at each
    /// flash operation: after every cut the older or the newer record
    /// loads, never nothing.
    #[test]
    fn flash_store_restore_with_cuts(p: Peripherals) {
        let flash_ok = board::check_flash().is_ok();
        assert!(flash_ok, "flash layout: dual bank, 512 KiB expected");
        let mut raw = Some(flash::BoardFlash::new(p.FLASH, true));
        let with = |id: u8| {
            let mut par = Params::factory();
            par.can.node_id = id;
            par
        };
        let mut whole = false;
        for n in 0..64u32 {
            let inner = raw.take().expect("flash driver");
            let store = SeqStore::new(cut::CutFlash::new(EccGuard::new(inner)), flash::STORAGE);
            let mut st = store.expect("storage range");
            st.erase_all().expect("erase");
            save(&mut st, &with(0x21)).expect("first save");
            st.flash_mut().cut_after(n);
            let cut = save(&mut st, &with(0x22)).is_err();
            st.flash_mut().cut_after(u32::MAX);
            let (par, boot) = load(&mut st);
            assert_eq!(boot, Boot::Stored);
            assert!(matches!(par.can.node_id, 0x21 | 0x22), "mixed record");
            raw = Some(st.into_flash().into_inner().into_inner());
            if !cut {
                whole = true;
                break;
            }
        }
        assert!(
            whole,
            "a store took more than 64 flash operations: not every cut tried"
        );
    }

    /// The ECC path on the part: a guarded read of the storage pages
    /// reports no error and leaves ECCC/ECCD clear (see the module docs:
    /// no fault can be injected by software on the STM32G4).
    #[test]
    fn ecc_clean_read_keeps_detection_armed(p: Peripherals) {
        let mut f = EccGuard::new(flash::BoardFlash::new(
            p.FLASH,
            board::check_flash().is_ok(),
        ));
        let mut buf = [0u8; 64];
        let r = embassy_futures::block_on(perpend_board::storage::nor_flash::ReadNorFlash::read(
            &mut f,
            flash::STORAGE.start,
            &mut buf,
        ));
        assert!(r.is_ok());
        assert_eq!(f.last_fault(), None);
        let e = pac::FLASH.eccr().read();
        assert!(
            !e.eccc() && !e.eccd(),
            "ECC flags left set: detection disarmed"
        );
    }

    /// After the probe's reset the cause is the pin or a software reset,
    /// never a watchdog, and the flags are cleared by reading them.
    #[test]
    fn reset_cause(_p: Peripherals) {
        use perpend_board::health::ResetCause;
        let first = board::take_reset_flags();
        assert!(
            matches!(
                first.cause(),
                ResetCause::Pin | ResetCause::Software | ResetCause::PowerOn
            ),
            "unexpected reset cause"
        );
        assert_eq!(board::take_reset_flags().cause(), ResetCause::Unknown);
    }

    /// The painted stack with the MPU guard: unbounded recursion faults
    /// (the fault handlers end the test as passed).
    #[test]
    fn stack_guard_faults(_p: Peripherals) {
        board::paint_and_guard_stack();
        EXPECT_FAULT.store(true, Ordering::SeqCst);
        let depth = recurse(core::hint::black_box(1));
        panic!("recursion returned at depth {depth}: no fault");
    }

    /// The IWDG at the firmware's 500 ms, taken over from the bootloader's
    /// 8 s as the firmware does (`board::Watchdog::take_over`, issue 50
    /// item 2): the period from PR/RLR (LSI 32 kHz) within 1 %; 400 ms
    /// without a pet right after the hand-over survive (embassy's
    /// `IndependentWatchdog::new` left 125 ms: the part reset here); then
    /// petting every 100 ms keeps the part alive for 2 s. Runs last: the
    /// IWDG cannot be stopped.
    #[test]
    async fn zz_iwdg(_p: Peripherals) {
        let (mut wdg, r) = board::Watchdog::take_over(500_000);
        assert!(r.is_ok(), "PVU/RVU stuck");
        embassy_time::Timer::after_millis(400).await;
        let pr = u32::from(pac::IWDG.pr().read().pr().to_bits());
        let rlr = u32::from(pac::IWDG.rlr().read().rl());
        let period_us = (4u32 << pr) * (rlr + 1) * 1_000 / 32;
        assert!(period_us.abs_diff(500_000) <= 5_000, "IWDG period");
        for _ in 0..20 {
            wdg.pet();
            embassy_time::Timer::after_millis(100).await;
        }
    }
}

/// Recursion with a 256-byte frame until the stack runs out.
#[inline(never)]
fn recurse(n: u32) -> u32 {
    if n == u32::MAX {
        return n;
    }
    let mut pad = [0u8; 256];
    pad[n as usize % 256] = n as u8;
    core::hint::black_box(&mut pad);
    recurse(n + 1).wrapping_add(u32::from(pad[0]))
}

mod cut {
    //! A NOR flash whose operations are refused after a chosen number: the
    //! store cut at each step on the part.

    use perpend_board::storage::nor_flash::{
        ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
    };
    use perpend_board::storage::FlashHealth;

    /// Refused (the cut) or the inner flash's error.
    #[derive(Debug)]
    pub enum CutError<E> {
        /// The operation was refused: the power was "cut".
        Cut,
        /// The inner flash failed.
        Inner(E),
    }

    impl<E: NorFlashError> NorFlashError for CutError<E> {
        fn kind(&self) -> NorFlashErrorKind {
            match self {
                Self::Cut => NorFlashErrorKind::Other,
                Self::Inner(e) => e.kind(),
            }
        }
    }

    /// `inner` with erases and writes refused after `left` more.
    pub struct CutFlash<F> {
        inner: F,
        left: u32,
    }

    impl<F> CutFlash<F> {
        /// No cut scheduled.
        pub fn new(inner: F) -> Self {
            Self {
                inner,
                left: u32::MAX,
            }
        }
        /// Refuses erases and writes after `n` more.
        pub fn cut_after(&mut self, n: u32) {
            self.left = n;
        }
        /// The inner flash.
        pub fn into_inner(self) -> F {
            self.inner
        }
        fn step(&mut self) -> bool {
            let ok = self.left > 0;
            self.left = self.left.saturating_sub(1);
            ok
        }
    }

    impl<F: ErrorType> ErrorType for CutFlash<F> {
        type Error = CutError<F::Error>;
    }

    impl<F: ReadNorFlash> ReadNorFlash for CutFlash<F> {
        const READ_SIZE: usize = F::READ_SIZE;
        async fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
            self.inner
                .read(offset, bytes)
                .await
                .map_err(CutError::Inner)
        }
        fn capacity(&self) -> usize {
            self.inner.capacity()
        }
    }

    impl<F: NorFlash> NorFlash for CutFlash<F> {
        const WRITE_SIZE: usize = F::WRITE_SIZE;
        const ERASE_SIZE: usize = F::ERASE_SIZE;
        async fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
            if !self.step() {
                return Err(CutError::Cut);
            }
            self.inner.erase(from, to).await.map_err(CutError::Inner)
        }
        async fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
            if !self.step() {
                return Err(CutError::Cut);
            }
            self.inner
                .write(offset, bytes)
                .await
                .map_err(CutError::Inner)
        }
    }

    impl<F: FlashHealth> FlashHealth for CutFlash<F> {
        fn take_read_faults(&mut self) -> u32 {
            self.inner.take_read_faults()
        }
        fn supply_ok(&mut self) -> bool {
            self.inner.supply_ok()
        }
    }
}

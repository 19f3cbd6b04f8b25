//! The FDCAN1 receive side: hardware acceptance filters
//! ([`perpend_board::rxfilter`]) and a RAM ring filled by the FDCAN1
//! interrupt, so no frame is lost while the main loop is busy (a flash
//! store: up to ≈ 32 ms with a page erase).
//!
//! embassy-stm32 0.6 offers a buffered receiver (`Can::buffered`, an
//! `embassy-sync` channel filled in the IT0 interrupt), but it also takes
//! over transmission (its `TxMode::ClassicBuffered` makes `CanTx::write`
//! panic, and its ISR writes through the displacement that evicts the
//! wrong frame, see [`crate::can_tx`]). So the driver stays unbuffered and
//! [`RxInterrupt`], bound to FDCAN1_IT0 after embassy's handler (which
//! only clears IR.RFxN and wakes), empties Rx FIFO 0 then FIFO 1 into
//! [`RING`] by polling `CanRx::read` once per frame (it completes at once
//! while a FIFO holds a frame). The ISR runs during a store because the
//! board's flash driver ([`crate::flash`]) keeps interrupts enabled and
//! the code is in bank 1 (read-while-write).
//!
//! Ring size: [`RX_RING`] = 256 frames (3 KiB). The load test's worst
//! store (page erase 22 ms + 118 double words, 31.7 ms) under a SYNC at
//! 1 kHz plus a full-rate SDO flood to this node accepts 143 frames
//! (`rxfilter_tests.rs`); a flood of 0-byte frames at 100 % bus load
//! (47 µs each) would bring 674 in 31.7 ms and overflow it (counted,
//! EMCY 0x8110).

use core::cell::RefCell;
use core::future::poll_fn;
use core::sync::atomic::{AtomicU32, Ordering};
use core::task::{Poll, Waker};

use cortex_m::interrupt::Mutex;
use embassy_futures::poll_once;
use embassy_stm32::can::config::{FdCanConfig, GlobalFilter};
use embassy_stm32::can::filter::{Action, FilterType, StandardFilter, StandardFilterSlot};
use embassy_stm32::can::{CanRx, Properties};
use embassy_stm32::interrupt::typelevel::{Handler, FDCAN1_IT0};
use embedded_can::StandardId;
use heapless::Deque;
use perpend_board::busmon::PsrRead;
use perpend_board::rxfilter::{Fifo, StdFilter, MAX_STD_FILTERS};
use perpend_can::Frame;

/// A HAL frame as a perpend frame (`None` for extended identifiers, which
/// are not CANopen classic).
pub fn from_hal(f: &embassy_stm32::can::frame::Frame) -> Option<Frame> {
    let embedded_can::Id::Standard(id) = f.id() else {
        return None;
    };
    let mut out = Frame::new(id.as_raw(), f.data());
    if f.header().rtr() {
        out = Frame::remote(id.as_raw(), f.header().len());
    }
    Some(out)
}

/// Frames the RAM ring holds.
pub const RX_RING: usize = 256;

static RX: Mutex<RefCell<Option<CanRx<'static>>>> = Mutex::new(RefCell::new(None));
static RING: Mutex<RefCell<Deque<Frame, RX_RING>>> = Mutex::new(RefCell::new(Deque::new()));
static WAKER: Mutex<RefCell<Option<Waker>>> = Mutex::new(RefCell::new(None));
/// Frames lost because the ring was full.
pub static LOST: AtomicU32 = AtomicU32::new(0);
/// Most frames in the ring at once.
pub static PEAK: AtomicU32 = AtomicU32::new(0);

/// Hands the receiver to the interrupt.
pub fn install(rx: CanRx<'static>) {
    cortex_m::interrupt::free(|cs| RX.borrow(cs).replace(Some(rx)));
}

/// Frames waiting in both receive FIFOs (RXF0S.F0FL + RXF1S.F1FL).
pub fn fifo_fill() -> u32 {
    let r = embassy_stm32::pac::FDCAN1;
    u32::from(r.rxfs(0).read().ffl()) + u32::from(r.rxfs(1).read().ffl())
}

/// FDCAN1's PSR, read once per tick by `perpend_board::busmon::BusMonitor`
/// (the only PSR read of the firmware: every read resets PSR.LEC).
pub struct Psr;

impl PsrRead for Psr {
    fn read_psr(&mut self) -> u32 {
        embassy_stm32::pac::FDCAN1.psr().read().0
    }
}

/// Moves every frame waiting in the FIFOs into the ring (interrupt
/// context, or the main loop as a fallback). The driver's read is polled
/// only while a FIFO holds a frame: with both empty it would read PSR
/// (resetting LEC, which `BusMonitor` counts once per tick).
pub fn drain() {
    cortex_m::interrupt::free(|cs| {
        let mut rx = RX.borrow(cs).borrow_mut();
        let Some(rx) = rx.as_mut() else { return };
        let mut ring = RING.borrow(cs).borrow_mut();
        let mut got = false;
        // At most both FIFOs' worth plus one: never spins.
        for _ in 0..8 {
            if fifo_fill() == 0 {
                break;
            }
            match poll_once(rx.read()) {
                Poll::Ready(Ok(env)) => {
                    if let Some(f) = from_hal(&env.frame) {
                        if ring.push_back(f).is_err() {
                            LOST.fetch_add(1, Ordering::Relaxed);
                        }
                        got = true;
                    }
                }
                Poll::Ready(Err(_)) | Poll::Pending => break,
            }
        }
        PEAK.fetch_max(ring.len() as u32, Ordering::Relaxed);
        if got {
            if let Some(w) = WAKER.borrow(cs).borrow_mut().take() {
                w.wake();
            }
        }
    });
}

/// The next received frame (waits for the interrupt).
pub async fn next() -> Frame {
    poll_fn(|cx| {
        cortex_m::interrupt::free(|cs| match RING.borrow(cs).borrow_mut().pop_front() {
            Some(f) => Poll::Ready(f),
            None => {
                WAKER.borrow(cs).replace(Some(cx.waker().clone()));
                Poll::Pending
            }
        })
    })
    .await
}

/// FDCAN1_IT0, after embassy's handler: the FIFOs into the ring.
pub struct RxInterrupt;

impl Handler<FDCAN1_IT0> for RxInterrupt {
    unsafe fn on_interrupt() {
        drain();
    }
}

/// The global filter: reject every frame no element accepts, and remote
/// frames (RXGFC, RM0440 §44.4.22).
pub fn with_global_filter(c: FdCanConfig) -> FdCanConfig {
    c.set_global_filter(GlobalFilter::reject_all())
}

/// Writes the elements `filters` and disables the other slots (the
/// message RAM is undefined after reset).
pub fn program(props: &Properties, filters: &[StdFilter]) {
    for slot in 0..MAX_STD_FILTERS {
        let f = filters.get(slot).and_then(|f| {
            Some(StandardFilter {
                filter: FilterType::DedicatedDual(StandardId::new(f.id1)?, StandardId::new(f.id2)?),
                action: match f.fifo {
                    Fifo::F0 => Action::StoreInFifo0,
                    Fifo::F1 => Action::StoreInFifo1,
                },
            })
        });
        props.set_standard_filter(
            StandardFilterSlot::from(slot as u8),
            f.unwrap_or_else(StandardFilter::disable),
        );
    }
}

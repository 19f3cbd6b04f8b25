//! perpend sensor-board firmware (STM32G474RE, NUCLEO-G474RE wiring).
//!
//! A thin layer: every decision is made by `perpend_board::app::App`, the
//! same code the host's virtual board runs. This file only moves data
//! between the peripherals and the `App`:
//!
//! * **ADC1** converts the four sensor inputs and the internal temperature
//!   sensor in one scan, started by TIM3's update event (TRGO) every
//!   `period_us`, with 16× hardware oversampling; DMA1 channel 1 moves the
//!   results into a two-scan circular buffer (embassy's
//!   `RingBufferedAdc`, read one scan at a time). Reconfiguration and
//!   overrun recovery: [`acq_ctl`].
//! * **FDCAN1** in classic CAN mode, clocked from the 24 MHz HSE, with the
//!   explicit bit timing of `perpend_board::bittiming` (24 tq, sample point
//!   87.5 %, SJW 3 tq at every rate), Tx queue mode, automatic bus-off
//!   recovery by the driver; the recovery is reported as EMCY 0x8140.
//!   Frames leave through the software queue `perpend_board::txq` and
//!   [`can_tx::FdcanTx`]: nothing in the loop waits for the bus. Frames
//!   arrive through the acceptance filters of `perpend_board::rxfilter`
//!   and the interrupt-filled ring of [`can_rx`].
//! * **Flash**: the parameter storage in the last four 2 KiB pages of bank 2
//!   (`sequential-storage` via `perpend_board::storage::SeqStore`, over
//!   [`flash::BoardFlash`] behind `EccGuard`: interrupts stay enabled
//!   during erase/program, ECC double errors become skipped records, a low
//!   supply refuses the store).
//! * **Field update** ([`update`]): CiA 302-3 program download into
//!   embassy-boot's DFU partition (`perpend_board::dfu`), verified against
//!   the bootloader's public key before the swap is marked; the running
//!   image confirms itself (`mark_booted`) once storage, CAN and the first
//!   heartbeat or SYNC are up (`perpend_board::confirm`).
//! * **Health** ([`board`]): reset cause, VREF+ from VREFINT, die
//!   temperature, flash layout check, IWDG frozen under a debugger, DWT
//!   worst loop time, painted stack with an MPU guard, entry into the
//!   system bootloader (0x2500 = 0xB0).
//! * **IWDG** (500 ms) fed by the main loop only while samples arrive
//!   (last one < 20 ms ago) and the CAN controller is not stuck in bus-off
//!   (< 1 s). Taken over from the bootloader's 8 s at the end of `setup`
//!   with a reload (`perpend_board::bootctl::handover`): storage loading
//!   and repair run under the bootloader's 8 s, the loop starts with the
//!   full 500 ms.
//! * **Trial deadline**: an image on trial that has not confirmed itself
//!   60 s after boot resets, and the bootloader swaps the old one back
//!   (`perpend_board::confirm::TRIAL_DEADLINE_US`).
//! * **LED** LD2 (PA5): see `led_pattern`.
//!
//! All work runs in one task (`main`): a `select` over a 1 ms tick, "scan
//! ready" and "CAN frame received" (in that order, the frames within a
//! per-tick budget: `perpend_board::busmon`); frames the `App` emits go into the
//! transmit queue, which is serviced (never awaited) after each event.

#![no_std]
#![no_main]

mod acq_ctl;
mod board;
mod can_rx;
mod can_tx;
mod flash;
mod update;

use defmt::{info, warn};
use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_futures::select::{select3, Either3};
use embassy_stm32::adc::{AdcChannel, RingBufferedAdc};
use embassy_stm32::can::{self, CanConfigurator};
use embassy_stm32::gpio::{Level, Output, Speed};
use embassy_stm32::peripherals::{ADC1, DMA1_CH1, FDCAN1, PA11, PA12, TIM3};
use embassy_stm32::timer::low_level::{MasterMode, Timer};
use embassy_stm32::{bind_interrupts, dma, Peri};
use embassy_time::{Duration, Instant, Ticker};
use perpend_board::app::App;
use perpend_board::bittiming;
use perpend_board::busmon::{BusEvent, BusMonitor, RxBudget};
use perpend_board::health::{self, HealthError, LoopTimer, ResetCause};
use perpend_board::pipeline::Sample;
use perpend_board::rxfilter::{self, RxSet};
use perpend_board::storage::{Boot, EccGuard, SeqStore, BUF_LEN};
use perpend_board::txq::{TxQueue, TX_QUEUE_LEN};
use perpend_core::params::{Acquisition, Bitrate};
use static_cell::{ConstStaticCell, StaticCell};

use acq_ctl::SCAN;
use can_tx::FdcanTx;

bind_interrupts!(struct Irqs {
    FDCAN1_IT0 => can::IT0InterruptHandler<FDCAN1>, can_rx::RxInterrupt;
    FDCAN1_IT1 => can::IT1InterruptHandler<FDCAN1>;
    DMA1_CHANNEL1 => dma::InterruptHandler<DMA1_CH1>;
});

/// LED pattern: on = valid measurement; slow blink (1 Hz) = running without
/// a valid plane; fast blink (5 Hz) = factory defaults (uncalibrated) or a
/// configuration error.
fn led_pattern(status: u32, now_ms: u64) -> bool {
    use perpend_board::status::{CONFIG_INVALID, NO_PLANE, UNCALIBRATED};
    if status & (UNCALIBRATED | CONFIG_INVALID) != 0 {
        (now_ms / 100).is_multiple_of(2)
    } else if status & NO_PLANE != 0 {
        (now_ms / 500).is_multiple_of(2)
    } else {
        true
    }
}

/// The reset cause for the log (a `&str`, not `Debug2Format`: no
/// `core::fmt` in the image, issue 50 item 7).
fn reset_cause_name(c: ResetCause) -> &'static str {
    match c {
        ResetCause::PowerOn => "power-on",
        ResetCause::IndependentWatchdog => "independent watchdog",
        ResetCause::WindowWatchdog => "window watchdog",
        ResetCause::Software => "software",
        ResetCause::OptionLoad => "option byte loading",
        ResetCause::LowPower => "illegal low-power entry",
        ResetCause::Pin => "NRST pin",
        ResetCause::Unknown => "unknown",
    }
}

/// The flash layout error for the log.
fn flash_error_name(e: HealthError) -> &'static str {
    match e {
        HealthError::SingleBank => "single-bank (DBANK = 0)",
        HealthError::FlashTooSmall(_) => "too small",
    }
}

/// Panics: the location through defmt, then a fault (`udf`, as
/// panic-probe does, which a probe reports). The message is not printed:
/// formatting it would link `core::fmt` (≈ 3.7 KB, issue 50 item 7);
/// `defmt::panic!` logs its own message before it panics.
#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    cortex_m::interrupt::disable();
    match info.location() {
        Some(l) => defmt::error!("panicked at {=str}:{=u32}", l.file(), l.line()),
        None => defmt::error!("panicked"),
    }
    cortex_m::asm::udf()
}

/// FDCAN1 on PA11/PA12, classic CAN at `b` with the explicit bit timing,
/// Tx queue mode (lowest identifier first).
fn start_can(
    fdcan: Peri<'static, FDCAN1>,
    rx: Peri<'static, PA11>,
    tx: Peri<'static, PA12>,
    b: Bitrate,
) -> can::Can<'static> {
    let mut cc = CanConfigurator::new(fdcan, rx, tx, Irqs);
    can_tx::configure(&mut cc, b);
    cc.into_normal_mode()
}

/// The application as the board builds it.
type BoardApp = App<BoardStore, update::BoardDfu>;

/// The parameter storage: its item buffer is a static
/// ([`SeqStore::with_buffer`]), so that the store is moved into the app
/// without 2 KiB passing through `setup`'s frame (twice, as built).
type BoardStore = SeqStore<EccGuard<flash::BoardFlash>, &'static mut [u8; BUF_LEN]>;

/// The storage's item buffer.
static STORE_BUF: ConstStaticCell<[u8; BUF_LEN]> = ConstStaticCell::new([0; BUF_LEN]);

/// Where the application lives: built in place by [`App::init`] (≈ 11 KiB
/// that would otherwise pass through the main task's frame, issue 50
/// item 6).
static APP: StaticCell<BoardApp> = StaticCell::new();

/// The firmware's state between events.
struct Fw {
    app: &'static mut BoardApp,
    txq: TxQueue<TX_QUEUE_LEN>,
    can_tx: FdcanTx<'static>,
    props: can::Properties,
    ring: RingBufferedAdc<'static, ADC1>,
    tim: Timer<'static, TIM3>,
    acq: Acquisition,
    bitrate: Bitrate,
    led: Output<'static>,
    wdg: board::Watchdog,
    last_sample: Instant,
    /// Acquisition locked to SYNC (0x2301 sub 1): TIM3 stopped, one scan
    /// per SYNC.
    locked: bool,
    /// Bus errors and bus-off from one PSR read per tick.
    bus: BusMonitor,
    /// Frames the loop may still take before the next tick.
    rx_budget: RxBudget,
    samples: u32,
    /// What the acceptance filters are programmed for.
    rx_set: RxSet,
    /// Ring overflows already reported.
    rx_lost_seen: u32,
    /// VREF+ measured with VREFINT at boot [mV] (`None`: implausible, the
    /// record's `vref_mv` is used unchanged).
    vref_mv: Option<f32>,
    /// Factory TS_CAL1, TS_CAL2.
    ts_cal: (u16, u16),
    /// Worst main-loop turn (DWT cycles).
    loop_timer: LoopTimer,
    /// 1 ms ticks since boot.
    ticks: u32,
    /// The health figures (0x200B) are due.
    health_due: bool,
}

/// Microseconds since boot (the App's clock).
fn now_us() -> u64 {
    Instant::now().as_micros()
}

/// Where the App's frames go: the transmit queue. One closure type for
/// `App::handle` and `App::poll`: each type their `impl FnMut(Frame)` is
/// called with is one more copy of the device's send paths in flash
/// (`cargo xtask size`, issue 50 item 7).
fn to_queue(q: &mut TxQueue<TX_QUEUE_LEN>) -> impl FnMut(perpend_can::Frame) + '_ {
    move |o| {
        q.push(o);
    }
}

impl Fw {
    /// One ADC scan through the pipeline.
    fn on_scan(&mut self, scan: &[u16; SCAN]) {
        let t_acq = now_us();
        let assumed = f32::from(self.acq.vref_mv);
        let vref = self.vref_mv.unwrap_or(assumed);
        let c = |k: usize| health::correct_count(scan[k], vref, assumed);
        let (c1, c2) = self.ts_cal;
        let s = Sample {
            counts: [c(0), c(1), c(2), c(3)],
            temp_c: health::die_temp_c(scan[4], acq_ctl::scan_gain(&self.acq), vref, c1, c2),
            t_s: None,
        };
        let o = self.app.on_sample(&s, t_acq);
        self.last_sample = Instant::now();
        self.samples = self.samples.wrapping_add(1);
        if self.samples.is_multiple_of(1000) {
            info!(
                "sample {} status {=u32:#x} θ1 {} θ2 {} rms {} ({} µs), tx dropped {}, bus errors {}",
                self.samples,
                o.status,
                o.theta1_deg,
                o.theta2_deg,
                o.rms_mm,
                now_us() - t_acq,
                self.txq.stats().dropped,
                self.bus.errors()
            );
        }
    }

    /// A received frame to the application.
    fn on_frame(&mut self, f: &perpend_can::Frame) {
        self.app.handle(f, now_us(), &mut to_queue(&mut self.txq));
    }

    /// Reprograms the acceptance filters when what the node listens to
    /// changed (node-id, RPDO COB-IDs, heartbeat consumers).
    fn update_filters(&mut self) {
        let set = RxSet::from_device(self.app.device());
        if set == self.rx_set {
            return;
        }
        match rxfilter::filters(&set) {
            Ok(f) => {
                can_rx::program(&self.props, &f);
                info!("CAN acceptance filters: {} elements", f.len());
                self.rx_set = set;
            }
            Err(_) => warn!("CAN acceptance filters do not fit: unchanged"),
        }
    }

    /// The 1 ms tick: receive overrun, device timers, bus state, ADC
    /// overrun, LED, watchdog.
    fn on_tick(&mut self) {
        // FDCAN "Rx FIFO 0 message lost" (IR.RF0L, RM0440 §44.4.16):
        // frames were dropped because the FIFO was full. The HAL does not
        // report it; the App turns it into EMCY 0x8110. The flag is cleared
        // by writing 1 (other bits written 0 are kept).
        let ir = embassy_stm32::pac::FDCAN1.ir();
        let irv = ir.read();
        if irv.rfl(0) || irv.rfl(1) {
            ir.write(|w| {
                w.set_rfl(0, true);
                w.set_rfl(1, true);
            });
            warn!("CAN receive FIFO overrun");
            self.app.rx_overrun();
        }
        // Frames that arrived before the receiver was handed to the
        // interrupt (or any the interrupt left) go to the ring now.
        can_rx::drain();
        // The interrupt's RAM ring overflowed (frames lost too).
        let lost = can_rx::LOST.load(core::sync::atomic::Ordering::Relaxed);
        if lost != self.rx_lost_seen {
            self.rx_lost_seen = lost;
            warn!("CAN receive ring overflow: {} frames lost", lost);
            self.app.rx_overrun();
        }
        self.update_filters();
        self.ticks = self.ticks.wrapping_add(1);
        self.health_due |= self.ticks.is_multiple_of(1000);
        self.app.poll(now_us(), &mut to_queue(&mut self.txq));
        self.check_bus_off();
        self.confirm_boot();
        if self.app.trial_expired(now_us()) {
            warn!("image on trial not confirmed within 60 s: resetting, the bootloader reverts it");
            self.flush_tx();
            cortex_m::peripheral::SCB::sys_reset();
        }
        if acq_ctl::overrun() {
            warn!("ADC overrun: restarting the acquisition");
            acq_ctl::restart(&mut self.ring, &self.tim, &self.acq, self.locked);
        }
        let now = Instant::now();
        let on = led_pattern(self.app.last_output().status, now.as_millis());
        self.led
            .set_level(if on { Level::High } else { Level::Low });
        // Locked to SYNC, no SYNC means no sample: the controller's
        // business (0x2301 sub 2 counts SYNCs without their sample).
        let acq_alive = self.locked || now - self.last_sample < Duration::from_millis(20);
        let can_alive = self.bus.bus_off_for_us(now.as_micros()) < 1_000_000;
        if acq_alive && can_alive {
            self.wdg.pet();
        }
    }

    /// Confirms a freshly swapped-in image once it has come up completely
    /// (`perpend_board::confirm`): "CAN running" = FDCAN TXBTO shows a
    /// frame acknowledged on the bus (the App latches it).
    fn confirm_boot(&mut self) {
        let acked = embassy_stm32::pac::FDCAN1.txbto().read().0 & 0b111 != 0;
        match self.app.confirm_boot(acked) {
            Some(Ok(())) => info!("image confirmed (embassy-boot mark_booted)"),
            Some(Err(e)) => warn!(
                "image not confirmed (0x1F57 status {=u32:#x}): the bootloader reverts it at the next reset",
                e.flash_status()
            ),
            None => {}
        }
    }

    /// The tick's one PSR read: bus errors (PSR.LEC, e.g. one acknowledge
    /// error per retransmission when alone on the bus: counted, logged with
    /// the per-1000-sample line) and bus-off.
    fn check_bus_off(&mut self) {
        match self.bus.tick(&mut can_rx::Psr, now_us()) {
            BusEvent::BusOff => warn!("CAN bus-off"),
            BusEvent::Recovered => {
                info!("CAN bus-off recovered");
                self.app.bus_off_recovered();
            }
            BusEvent::None => {}
        }
    }

    /// After every event: configuration changes, then the transmit queue
    /// into the controller (never waits) and its counters to the App.
    fn after_event(&mut self) {
        if self.app.take_sync_scan() && self.locked {
            acq_ctl::trigger_scan(&self.tim);
        }
        if let Some(a) = self.app.take_acq_change() {
            self.locked = self.app.sync_locked();
            info!(
                "acquisition: {} µs, 2^{} oversampling, on SYNC {}",
                a.period_us, a.os_log2, self.locked
            );
            if !acq_ctl::restart(&mut self.ring, &self.tim, &a, self.locked) {
                warn!("ADC did not stop: oversampling may be unchanged");
            }
            self.acq = a;
        }
        if let Some(c) = self.app.take_can_change() {
            if c.bitrate != self.bitrate {
                warn!(
                    "bit rate {} bit/s takes effect at the next power-on (store it with 0x1010)",
                    c.bitrate.bps()
                );
            }
        }
        // LSS "activate bit timing" (CiA 305): the switch delay has passed.
        let lss = self.app.device_mut().take_bit_rate_switch();
        if let Some(b) = lss.and_then(perpend_can::config::bitrate_of) {
            // perpend_board::fdcan: pending frames read back and requeued,
            // an outstanding cancellation forgotten, FIFO losses counted.
            let sw = self.can_tx.switch_bitrate(bittiming::for_board(b).nbtp());
            let n = sw.requeue.len();
            for f in sw.requeue {
                self.txq.requeue(f);
            }
            if sw.rx_lost > 0 {
                warn!("LSS switch: {} received frames lost", sw.rx_lost);
                self.app.rx_overrun();
            }
            info!(
                "LSS: bit rate now {} bit/s ({} frames requeued)",
                b.bps(),
                n
            );
            self.bitrate = b;
        }
        self.txq.service(&mut self.can_tx);
        self.app.tx_stats(self.txq.stats(), now_us());
        if self.app.take_bootloader_request() {
            self.enter_bootloader();
        }
        if self.app.take_update_restart() {
            warn!("0x1F51 start: resetting into perpend-boot, which swaps the new image in");
            self.flush_tx();
            cortex_m::peripheral::SCB::sys_reset();
        }
    }

    /// Lets the SDO answer and what else is queued leave (at most 20 ms).
    fn flush_tx(&mut self) {
        let end = Instant::now() + Duration::from_millis(20);
        while Instant::now() < end {
            self.txq.service(&mut self.can_tx);
            let pending = embassy_stm32::pac::FDCAN1.txbrp().read().0 & 0b111;
            if self.txq.is_empty() && pending == 0 {
                break;
            }
        }
    }

    /// 0x2500 = bootloader in pre-operational: the SDO answer and what else
    /// is queued leave (at most 20 ms), then a reset into the ROM
    /// bootloader.
    fn enter_bootloader(&mut self) {
        warn!("0x2500: resetting into the system bootloader (field update)");
        self.flush_tx();
        if board::reset_into_bootloader().is_err() {
            warn!("0x2500: the bootloader does not allow the ROM loader (release build)");
        }
    }
}

/// ADC1 scanning the four `inputs` and the temperature sensor on TIM3's
/// TRGO into the DMA ring (started by [`acq_ctl::restart`]).
/// Brings up the peripherals and the application (a plain function, so
/// that its locals do not take room in the main task's future; not
/// inlined, so that they do not take room in the main task's frame either:
/// that frame stays on the stack while the loop runs).
#[inline(never)]
fn setup() -> Fw {
    let p = embassy_stm32::init(board::config());
    info!("perpend-fw {}", env!("CARGO_PKG_VERSION"));
    let reset = board::take_reset_flags();
    info!(
        "reset cause {=str} (RCC_CSR flags {=u8:#04x})",
        reset_cause_name(reset.cause()),
        reset.0
    );
    board::freeze_iwdg_in_debug();
    board::start_cycle_counter();
    board::paint_and_guard_stack();
    let flash_ok = match board::check_flash() {
        Ok(()) => true,
        Err(e) => {
            defmt::error!(
                "flash layout {=str} (DBANK {}, {} KiB): parameter storage disabled, factory defaults",
                flash_error_name(e),
                embassy_stm32::pac::FLASH.optr().read().dbank(),
                board::flash_size_kib()
            );
            false
        }
    };

    let led = Output::new(p.PA5, Level::Low, Speed::Low);

    // Parameters and the CANopen device.
    flash::enable_pvd();
    let flash = EccGuard::new(flash::BoardFlash::new(p.FLASH, flash_ok));
    let store = match SeqStore::with_buffer(flash, flash::STORAGE, STORE_BUF.take()) {
        Ok(s) => s,
        Err(_) => defmt::panic!("storage range is not a valid map range"),
    };
    // 0x1018 sub 4: the 96-bit unique ID folded to 32 bits.
    let serial = perpend_can::config::serial_from_uid(&embassy_stm32::uid::uid());
    info!("serial number {=u32:#010x}", serial);
    let app = App::init(APP.uninit(), store, serial, update::program(flash_ok));
    app.report_reset(reset);
    app.report_option_bytes(board::optr());
    let policy = board::rom_loader_policy();
    app.set_rom_loader_policy(policy);
    if policy.test_key {
        warn!("bootloader built with the TEST key (keys/test-only.pk): never ship this board");
    }
    if app.on_trial() {
        warn!("image on trial: confirms itself once up, else reverted after 60 s");
    }
    if app.boot_read_faults() > 0 {
        warn!(
            "boot: {} unreadable flash double word(s) (ECC) skipped",
            app.boot_read_faults()
        );
    }
    match app.boot() {
        Boot::Stored => info!("boot: stored parameters"),
        Boot::Missing => info!("boot: no stored parameters, factory defaults (uncalibrated)"),
        Boot::Rejected(_) => warn!("boot: stored record rejected, factory defaults"),
        Boot::Unreadable(_) => warn!("boot: storage unreadable, factory defaults"),
    }
    let can_cfg = app.can_config();
    let acq = app.acquisition();
    let app_locked = app.sync_locked();

    let (tx, rx, props) = start_can(p.FDCAN1, p.PA11, p.PA12, can_cfg.bitrate).split();
    let rx_set = RxSet::from_device(app.device());
    match rxfilter::filters(&rx_set) {
        Ok(f) => can_rx::program(&props, &f),
        Err(_) => defmt::panic!("CAN acceptance filters do not fit"),
    }
    can_rx::install(rx);
    info!(
        "CAN node {} at {} bit/s",
        can_cfg.node_id,
        can_cfg.bitrate.bps()
    );

    // ADC1: PA0 (IN1), PA1 (IN2), PB0 (IN15), PC1 (IN7) + temperature.
    let inputs = [
        p.PA0.degrade_adc(),
        p.PA1.degrade_adc(),
        p.PB0.degrade_adc(),
        p.PC1.degrade_adc(),
    ];
    let (ring, vref_mv) = acq_ctl::start(p.ADC1, p.DMA1_CH1, inputs, &acq, Irqs);
    match vref_mv {
        Some(v) => info!("VREF+ {} mV (VREFINT), assumed {} mV", v, acq.vref_mv),
        None => warn!("VREFINT implausible: VREF+ taken as {} mV", acq.vref_mv),
    }
    let (_, ts1, ts2) = board::factory_cal();
    // TIM3 update event = scan trigger.
    let tim = Timer::new(p.TIM3);
    tim.set_master_mode(MasterMode::UPDATE);

    // The bootloader's 8 s covered everything above (storage load and
    // repair included); from here the loop's 500 ms, reloaded now.
    let (wdg, wdg_result) = board::Watchdog::take_over(500_000);
    let mut fw = Fw {
        app,
        txq: TxQueue::new(),
        can_tx: can_tx::new(tx),
        props,
        ring,
        tim,
        acq,
        bitrate: can_cfg.bitrate,
        led,
        wdg,
        last_sample: Instant::now(),
        locked: app_locked,
        bus: BusMonitor::new(),
        rx_budget: RxBudget::new(),
        samples: 0,
        rx_set,
        rx_lost_seen: 0,
        vref_mv,
        ts_cal: (ts1, ts2),
        loop_timer: LoopTimer::default(),
        ticks: 0,
        health_due: false,
    };
    acq_ctl::restart(&mut fw.ring, &fw.tim, &fw.acq, fw.locked);
    if wdg_result.is_err() {
        warn!("IWDG hand-over: PR/RLR update still pending (PVU/RVU), counter reloaded anyway");
    }
    fw
}

#[embassy_executor::main]
async fn main(_spawner: Spawner) {
    let mut fw = setup();

    let mut ticker = Ticker::every(Duration::from_millis(1));
    let mut scan = [0u16; SCAN];
    loop {
        // perpend_board::busmon::pick: the tick first (IWDG, bus-off), then
        // a scan, then a frame while the tick's budget allows (a receive
        // flood cannot starve the tick; select3 polls in this order).
        let allow = fw.rx_budget.allows();
        let frame = async {
            if allow {
                can_rx::next().await
            } else {
                core::future::pending().await
            }
        };
        let event = select3(ticker.next(), fw.ring.read(&mut scan), frame).await;
        let t0 = board::cycles();
        match event {
            Either3::First(()) => {
                fw.rx_budget.on_tick();
                fw.on_tick();
            }
            Either3::Second(Ok(_)) => fw.on_scan(&scan),
            Either3::Second(Err(_)) => {
                warn!("ADC DMA overrun: restarting the acquisition");
                acq_ctl::restart(&mut fw.ring, &fw.tim, &fw.acq, fw.locked);
            }
            Either3::Third(f) => {
                fw.rx_budget.on_frame();
                fw.on_frame(&f);
            }
        }
        fw.after_event();
        fw.loop_timer.record(t0, board::cycles());
        // Outside the timed turn: the health figures once a second.
        if core::mem::take(&mut fw.health_due) {
            let vref = fw.vref_mv.map_or(0, |v| v as u32);
            let stack = board::stack_used() as u32;
            fw.app.set_health(fw.loop_timer.worst(), stack, vref);
        }
    }
}

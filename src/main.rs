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
//!   [`can_tx::FdcanTx`]: nothing in the loop waits for the bus.
//! * **Flash**: the parameter storage in the last four 2 KiB pages of bank 2
//!   (`sequential-storage` via `perpend_board::storage::SeqStore`).
//! * **IWDG** (500 ms) fed by the main loop only while samples arrive
//!   (last one < 20 ms ago) and the CAN controller is not stuck in bus-off
//!   (< 1 s).
//! * **LED** LD2 (PA5): see `led_pattern`.
//!
//! All work runs in one task (`main`): a `select` over "scan ready", "CAN
//! frame received" and a 1 ms tick; frames the `App` emits go into the
//! transmit queue, which is serviced (never awaited) after each event.

#![no_std]
#![no_main]

mod acq_ctl;
mod can_tx;

use core::num::{NonZeroU16, NonZeroU8};

use defmt::{info, warn};
use embassy_embedded_hal::adapter::BlockingAsync;
use embassy_executor::Spawner;
use embassy_futures::select::{select3, Either3};
use embassy_stm32::adc::{
    Adc, AdcChannel, AdcConfig, AnyAdcChannel, Exten, RingBufferedAdc, SampleTime,
};
use embassy_stm32::can::config::{NominalBitTiming, TxBufferMode};
use embassy_stm32::can::enums::BusErrorMode;
use embassy_stm32::can::{self, CanConfigurator};
use embassy_stm32::flash::{Blocking, Flash};
use embassy_stm32::gpio::{Level, Output, Speed};
use embassy_stm32::peripherals::{ADC1, DMA1_CH1, FDCAN1, IWDG, PA11, PA12, TIM3};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::low_level::{MasterMode, Timer};
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::{bind_interrupts, dma, rcc, Config, Peri};
use embassy_time::{Duration, Instant, Ticker};
use perpend_board::app::App;
use perpend_board::bittiming::{self, FDCAN_KERNEL_HZ};
use perpend_board::pipeline::Sample;
use perpend_board::storage::{Boot, SeqStore};
use perpend_board::txq::{TxQueue, TX_QUEUE_LEN};
use perpend_core::params::{Acquisition, Bitrate};
use {defmt_rtt as _, panic_probe as _};

use acq_ctl::{RING_LEN, SCAN};
use can_tx::{from_hal, FdcanTx};

bind_interrupts!(struct Irqs {
    FDCAN1_IT0 => can::IT0InterruptHandler<FDCAN1>;
    FDCAN1_IT1 => can::IT1InterruptHandler<FDCAN1>;
    DMA1_CHANNEL1 => dma::InterruptHandler<DMA1_CH1>;
});

/// Storage range (flash offsets): the last four 2 KiB pages of bank 2,
/// 0x0807E000..0x08080000, outside FLASH in memory.x.
const STORAGE: core::ops::Range<u32> = 0x7_E000..0x8_0000;

/// Factory-calibrated temperature sensor readings (RM0440 §21.4.32): 12-bit
/// raw values at 30 °C and 130 °C, taken with VREF+ = 3.0 V.
const TS_CAL1: *const u16 = 0x1FFF_75A8 as *const u16;
const TS_CAL2: *const u16 = 0x1FFF_75CA as *const u16;

/// Die temperature [°C] from a raw (oversampled) result: the thermal
/// extension's head temperature (the board sits in the head; the die
/// temperature is its proxy).
fn die_temp_c(raw: u16, acq: &Acquisition) -> Option<f32> {
    // SAFETY: the calibration words are in the system memory of every
    // STM32G4 and always readable.
    let (c1, c2) = unsafe { (TS_CAL1.read_volatile(), TS_CAL2.read_volatile()) };
    if c2 <= c1 {
        return None;
    }
    let gain = (1u32 << acq.os_log2) as f32 / (1u32 << acq.os_shift) as f32;
    // result at VREF+ = vref, scaled to the 3.0 V of the calibration
    let raw12 = raw as f32 / gain * (acq.vref_mv as f32 / 3000.0);
    Some((raw12 - c1 as f32) * 100.0 / (c2 as f32 - c1 as f32) + 30.0)
}

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

fn config() -> Config {
    let mut c = Config::default();
    // NUCLEO-G474RE: 24 MHz crystal (X3). SYSCLK = 24 / 6 * 85 / 2 = 170 MHz.
    c.rcc.hse = Some(rcc::Hse {
        freq: Hertz(FDCAN_KERNEL_HZ),
        mode: rcc::HseMode::Oscillator,
    });
    c.rcc.pll = Some(rcc::Pll {
        source: rcc::PllSource::HSE,
        prediv: rcc::PllPreDiv::DIV6,
        mul: rcc::PllMul::MUL85,
        divp: None,
        divq: None,
        divr: Some(rcc::PllRDiv::DIV2),
    });
    c.rcc.sys = rcc::Sysclk::PLL1_R;
    c.rcc.boost = true;
    // FDCAN from HSE: the kernel clock of perpend_board::bittiming.
    c.rcc.mux.fdcansel = rcc::mux::Fdcansel::HSE;
    // ADC from SYSCLK (the driver divides by 4: 42.5 MHz ≤ 60 MHz).
    c.rcc.mux.adc12sel = rcc::mux::Adcsel::SYS;
    c
}

/// The board's FDCAN nominal bit timing for `b` as the driver's type
/// (`None` only if the table held a value the type cannot).
fn nominal_timing(b: Bitrate) -> Option<NominalBitTiming> {
    let t = bittiming::for_board(b);
    Some(NominalBitTiming {
        prescaler: NonZeroU16::new(t.prescaler)?,
        seg1: NonZeroU8::new(u8::try_from(t.seg1).ok()?)?,
        seg2: NonZeroU8::new(t.seg2)?,
        sync_jump_width: NonZeroU8::new(t.sjw)?,
    })
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
    match nominal_timing(b) {
        Some(nbt) => {
            let c = cc.config().set_nominal_bit_timing(nbt);
            cc.set_config(c.set_tx_buffer_mode(TxBufferMode::Priority));
        }
        None => cc.set_bitrate(b.bps()),
    }
    info!("FDCAN NBTP {=u32:#010x}", bittiming::for_board(b).nbtp());
    cc.into_normal_mode()
}

/// The firmware's state between events.
struct Fw {
    app: App<SeqStore<BlockingAsync<Flash<'static, Blocking>>>>,
    txq: TxQueue<TX_QUEUE_LEN>,
    can_tx: FdcanTx<'static>,
    props: can::Properties,
    ring: RingBufferedAdc<'static, ADC1>,
    tim: Timer<'static, TIM3>,
    acq: Acquisition,
    bitrate: Bitrate,
    led: Output<'static>,
    wdg: IndependentWatchdog<'static, IWDG>,
    last_sample: Instant,
    /// Acquisition locked to SYNC (0x2301 sub 1): TIM3 stopped, one scan
    /// per SYNC.
    locked: bool,
    bus_off_since: Option<Instant>,
    samples: u32,
    /// Bus errors seen by the receive side (PSR.LEC, e.g. one acknowledge
    /// error per retransmission when alone on the bus): counted, logged
    /// with the per-1000-sample line, not one warning each.
    bus_errors: u32,
}

/// Microseconds since boot (the App's clock).
fn now_us() -> u64 {
    Instant::now().as_micros()
}

impl Fw {
    /// One ADC scan through the pipeline.
    fn on_scan(&mut self, scan: &[u16; SCAN]) {
        let t_acq = now_us();
        let s = Sample {
            counts: [scan[0], scan[1], scan[2], scan[3]],
            temp_c: die_temp_c(scan[4], &self.acq),
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
                self.bus_errors
            );
        }
    }

    /// A received frame to the application.
    fn on_frame(&mut self, f: &can::frame::Frame) {
        if let Some(f) = from_hal(f) {
            let q = &mut self.txq;
            self.app.handle(&f, now_us(), &mut |o| {
                q.push(o);
            });
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
        if ir.read().rfl(0) {
            ir.write(|w| w.set_rfl(0, true));
            warn!("CAN receive FIFO overrun");
            self.app.rx_overrun();
        }
        let q = &mut self.txq;
        self.app.poll(now_us(), &mut |o| {
            q.push(o);
        });
        self.check_bus_off();
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
        let can_alive = self
            .bus_off_since
            .is_none_or(|t| now - t < Duration::from_secs(1));
        if acq_alive && can_alive {
            self.wdg.pet();
        }
    }

    fn check_bus_off(&mut self) {
        match (self.props.bus_error_mode(), self.bus_off_since) {
            (BusErrorMode::BusOff, None) => {
                warn!("CAN bus-off");
                self.bus_off_since = Some(Instant::now());
            }
            (BusErrorMode::BusOff, Some(_)) | (_, None) => {}
            (_, Some(_)) => {
                info!("CAN bus-off recovered");
                self.bus_off_since = None;
                self.app.bus_off_recovered();
            }
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
        self.txq.service(&mut self.can_tx);
        self.app.tx_stats(self.txq.stats(), now_us());
    }
}

/// ADC1 scanning the four `inputs` and the temperature sensor on TIM3's
/// TRGO into the DMA ring (started by [`acq_ctl::restart`]).
fn start_adc(
    adc1: Peri<'static, ADC1>,
    dma: Peri<'static, DMA1_CH1>,
    inputs: [AnyAdcChannel<'static, ADC1>; 4],
    acq: &Acquisition,
) -> RingBufferedAdc<'static, ADC1> {
    let adc = Adc::new(
        adc1,
        AdcConfig {
            oversampling_ratio: Some(acq.os_log2.clamp(1, 8) - 1),
            oversampling_shift: Some(acq.os_shift),
            oversampling_mode: Some((
                embassy_stm32::pac::adc::vals::Rovsm::CONTINUED,
                embassy_stm32::pac::adc::vals::Trovs::AUTOMATIC,
                acq.os_log2 > 0,
            )),
            ..AdcConfig::default()
        },
    );
    let temp = adc.enable_temperature();
    // Sample times of perpend_board::scan (the 0x2300 period check):
    // SENSOR_SAMPLE_HALF_CYCLES = 95 (47.5), TEMP_SAMPLE_HALF_CYCLES = 495.
    let st = SampleTime::CYCLES47_5;
    let [a, b, c, d] = inputs;
    let seq = [
        (a, st),
        (b, st),
        (c, st),
        (d, st),
        (temp.degrade_adc(), SampleTime::CYCLES247_5),
    ];
    static mut DMA_BUF: [u16; RING_LEN] = [0; RING_LEN];
    // SAFETY: the only reference to the buffer, taken once before the loop.
    let dma_buf: &'static mut [u16; RING_LEN] = unsafe { &mut *core::ptr::addr_of_mut!(DMA_BUF) };
    adc.into_ring_buffered(
        dma,
        dma_buf,
        Irqs,
        seq.into_iter(),
        embassy_stm32::triggers::TIM3_TRGO,
        Exten::RISING_EDGE,
    )
}

/// Brings up the peripherals and the application (a plain function, so
/// that its locals do not take room in the main task's future).
fn setup() -> (Fw, can::CanRx<'static>) {
    let p = embassy_stm32::init(config());
    info!("perpend-fw {}", env!("CARGO_PKG_VERSION"));

    let led = Output::new(p.PA5, Level::Low, Speed::Low);
    let mut wdg = IndependentWatchdog::new(p.IWDG, 500_000);
    wdg.unleash();

    // Parameters and the CANopen device.
    let flash = BlockingAsync::new(Flash::new_blocking(p.FLASH));
    let store = match SeqStore::new(flash, STORAGE) {
        Ok(s) => s,
        Err(_) => defmt::panic!("storage range is not a valid map range"),
    };
    // 0x1018 sub 4: the 96-bit unique ID folded to 32 bits.
    let serial = perpend_can::config::serial_from_uid(&embassy_stm32::uid::uid());
    info!("serial number {=u32:#010x}", serial);
    let app = App::with_serial(store, serial);
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
    let ring = start_adc(p.ADC1, p.DMA1_CH1, inputs, &acq);
    // TIM3 update event = scan trigger.
    let tim = Timer::new(p.TIM3);
    tim.set_master_mode(MasterMode::UPDATE);

    let mut fw = Fw {
        app,
        txq: TxQueue::new(),
        can_tx: FdcanTx::new(tx),
        props,
        ring,
        tim,
        acq,
        bitrate: can_cfg.bitrate,
        led,
        wdg,
        last_sample: Instant::now(),
        locked: app_locked,
        bus_off_since: None,
        samples: 0,
        bus_errors: 0,
    };
    acq_ctl::restart(&mut fw.ring, &fw.tim, &fw.acq, fw.locked);
    (fw, rx)
}

#[embassy_executor::main]
async fn main(_spawner: Spawner) {
    let (mut fw, mut rx) = setup();

    let mut ticker = Ticker::every(Duration::from_millis(1));
    let mut scan = [0u16; SCAN];
    loop {
        match select3(fw.ring.read(&mut scan), rx.read(), ticker.next()).await {
            Either3::First(Ok(_)) => fw.on_scan(&scan),
            Either3::First(Err(_)) => {
                warn!("ADC DMA overrun: restarting the acquisition");
                acq_ctl::restart(&mut fw.ring, &fw.tim, &fw.acq, fw.locked);
            }
            Either3::Second(Ok(env)) => fw.on_frame(&env.frame),
            Either3::Second(Err(_)) => fw.bus_errors = fw.bus_errors.wrapping_add(1),
            Either3::Third(()) => fw.on_tick(),
        }
        fw.after_event();
    }
}

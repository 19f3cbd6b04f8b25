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
//!   `RingBufferedAdc`, read one scan at a time).
//! * **FDCAN1** in classic CAN mode, clocked from the 24 MHz HSE (1 Mbit/s =
//!   24 time quanta exactly), automatic bus-off recovery by the driver; the
//!   recovery is reported as EMCY 0x8140.
//! * **Flash**: the parameter storage in the last four 2 KiB pages of bank 2
//!   (`sequential-storage` via `perpend_board::storage::SeqStore`).
//! * **IWDG** (500 ms) fed by the main loop only while samples arrive
//!   (last one < 20 ms ago) and the CAN controller is not stuck in bus-off
//!   (< 1 s).
//! * **LED** LD2 (PA5): see `led_pattern`.
//!
//! All work runs in one task (`main`): a `select` over "scan ready", "CAN
//! frame received" and a 1 ms tick; frames the `App` emits are queued and
//! written after each event.

#![no_std]
#![no_main]

use defmt::{info, warn};
use embassy_embedded_hal::adapter::BlockingAsync;
use embassy_executor::Spawner;
use embassy_futures::select::{select3, Either3};
use embassy_stm32::adc::{Adc, AdcChannel, AdcConfig, Exten, SampleTime};
use embassy_stm32::can::enums::BusErrorMode;
use embassy_stm32::can::{self, CanConfigurator};
use embassy_stm32::flash::Flash;
use embassy_stm32::gpio::{Level, Output, Speed};
use embassy_stm32::peripherals::{DMA1_CH1, FDCAN1};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::low_level::{MasterMode, RoundTo, Timer};
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::{bind_interrupts, dma, rcc, Config};
use embassy_time::{Duration, Instant, Ticker};
use heapless::Deque;
use perpend_board::app::App;
use perpend_board::pipeline::Sample;
use perpend_board::storage::{Boot, SeqStore};
use perpend_can::Frame;
use perpend_core::params::Acquisition;
use {defmt_rtt as _, panic_probe as _};

bind_interrupts!(struct Irqs {
    FDCAN1_IT0 => can::IT0InterruptHandler<FDCAN1>;
    FDCAN1_IT1 => can::IT1InterruptHandler<FDCAN1>;
    DMA1_CHANNEL1 => dma::InterruptHandler<DMA1_CH1>;
});

/// Storage range (flash offsets): the last four 2 KiB pages of bank 2,
/// 0x0807E000..0x08080000, outside FLASH in memory.x.
const STORAGE: core::ops::Range<u32> = 0x7_E000..0x8_0000;

/// Channels per scan: four sensors, then the temperature sensor.
const SCAN: usize = 5;
/// Frames the App may emit per event before they are written.
const TX_QUEUE: usize = 32;

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

fn to_hal(f: &Frame) -> Option<can::frame::Frame> {
    if f.rtr {
        can::frame::Frame::new_remote(embedded_can::StandardId::new(f.id)?, f.len as usize).ok()
    } else {
        can::frame::Frame::new_standard(f.id, f.payload()).ok()
    }
}

fn from_hal(f: &can::frame::Frame) -> Option<Frame> {
    let embedded_can::Id::Standard(id) = f.id() else {
        return None; // extended ids are not CANopen classic: dropped
    };
    let mut out = Frame::new(id.as_raw(), f.data());
    if f.header().rtr() {
        out = Frame::remote(id.as_raw(), f.header().len());
    }
    Some(out)
}

fn config() -> Config {
    let mut c = Config::default();
    // NUCLEO-G474RE: 24 MHz crystal (X3). SYSCLK = 24 / 6 * 85 / 2 = 170 MHz.
    c.rcc.hse = Some(rcc::Hse {
        freq: Hertz::mhz(24),
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
    // FDCAN from HSE: 1 Mbit/s = 24 tq, 500/250/125 kbit/s exact as well.
    c.rcc.mux.fdcansel = rcc::mux::Fdcansel::HSE;
    // ADC from SYSCLK (the driver divides by 4: 42.5 MHz ≤ 60 MHz).
    c.rcc.mux.adc12sel = rcc::mux::Adcsel::SYS;
    c
}

/// Writes the ADC1 oversampling registers (the ADC must be stopped).
fn set_oversampling(acq: &Acquisition) {
    use embassy_stm32::pac;
    let ratio = acq.os_log2.clamp(1, 8) - 1; // OVSR: 0 = 2x .. 7 = 256x
    pac::ADC1.cfgr2().modify(|w| {
        w.set_rovse(acq.os_log2 > 0);
        w.set_ovsr(ratio);
        w.set_ovss(acq.os_shift.min(8));
    });
}

#[embassy_executor::main]
async fn main(_spawner: Spawner) {
    let p = embassy_stm32::init(config());
    info!("perpend-fw {}", env!("CARGO_PKG_VERSION"));

    let mut led = Output::new(p.PA5, Level::Low, Speed::Low);
    let mut wdg = IndependentWatchdog::new(p.IWDG, 500_000);
    wdg.unleash();

    // Parameters and the CANopen device.
    let flash = BlockingAsync::new(Flash::new_blocking(p.FLASH));
    let store = match SeqStore::new(flash, STORAGE) {
        Ok(s) => s,
        Err(_) => defmt::panic!("storage range is not a valid map range"),
    };
    let mut app = App::new(store);
    match app.boot() {
        Boot::Stored => info!("boot: stored parameters"),
        Boot::Missing => info!("boot: no stored parameters, factory defaults (uncalibrated)"),
        Boot::Rejected(_) => warn!("boot: stored record rejected, factory defaults"),
        Boot::Unreadable(_) => warn!("boot: storage unreadable, factory defaults"),
    }
    let can_cfg = app.can_config();
    let mut acq = app.acquisition();

    // CAN.
    let mut cc = CanConfigurator::new(p.FDCAN1, p.PA11, p.PA12, Irqs);
    cc.set_bitrate(can_cfg.bitrate.bps());
    let (mut tx, mut rx, props) = cc.into_normal_mode().split();
    info!(
        "CAN node {} at {} bit/s",
        can_cfg.node_id,
        can_cfg.bitrate.bps()
    );

    // ADC1: PA0 (IN1), PA1 (IN2), PB0 (IN15), PC1 (IN7) + temperature.
    let adc = Adc::new(
        p.ADC1,
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
    let st = SampleTime::CYCLES47_5;
    let seq = [
        (p.PA0.degrade_adc(), st),
        (p.PA1.degrade_adc(), st),
        (p.PB0.degrade_adc(), st),
        (p.PC1.degrade_adc(), st),
        (temp.degrade_adc(), SampleTime::CYCLES247_5),
    ];
    static mut DMA_BUF: [u16; 2 * SCAN] = [0; 2 * SCAN];
    // SAFETY: the only reference to the buffer, taken once before the loop.
    let dma_buf: &'static mut [u16; 2 * SCAN] = unsafe { &mut *core::ptr::addr_of_mut!(DMA_BUF) };
    let mut ring = adc.into_ring_buffered(
        p.DMA1_CH1,
        dma_buf,
        Irqs,
        seq.into_iter(),
        embassy_stm32::triggers::TIM3_TRGO,
        Exten::RISING_EDGE,
    );

    // TIM3 update event = scan trigger.
    let tim = Timer::new(p.TIM3);
    tim.set_master_mode(MasterMode::UPDATE);
    tim.set_frequency(Hertz(1_000_000 / acq.period_us), RoundTo::Slower);
    ring.start();
    tim.start();

    let mut ticker = Ticker::every(Duration::from_millis(1));
    let mut scan = [0u16; SCAN];
    let mut queue: Deque<Frame, TX_QUEUE> = Deque::new();
    let mut last_sample = Instant::now();
    let mut bus_off_since: Option<Instant> = None;
    let mut samples: u32 = 0;

    loop {
        let now_us = || Instant::now().as_micros();
        let mut push = |f: Frame| {
            if queue.push_back(f).is_err() {
                warn!("tx queue full: frame dropped");
            }
        };
        match select3(ring.read(&mut scan), rx.read(), ticker.next()).await {
            Either3::First(Ok(_)) => {
                let t_acq = now_us();
                let counts = [scan[0], scan[1], scan[2], scan[3]];
                let s = Sample {
                    counts,
                    temp_c: die_temp_c(scan[4], &acq),
                    t_s: None,
                };
                let o = app.on_sample(&s, t_acq);
                last_sample = Instant::now();
                samples = samples.wrapping_add(1);
                if samples.is_multiple_of(1000) {
                    info!(
                        "sample {} status {=u32:#x} θ1 {} θ2 {} rms {} ({} µs)",
                        samples,
                        o.status,
                        o.theta1_deg,
                        o.theta2_deg,
                        o.rms_mm,
                        now_us() - t_acq
                    );
                }
            }
            Either3::First(Err(_)) => {
                warn!("ADC DMA overrun: restarting the scan");
                ring.clear();
            }
            Either3::Second(Ok(env)) => {
                if let Some(f) = from_hal(&env.frame) {
                    app.handle(&f, now_us(), &mut push);
                }
            }
            Either3::Second(Err(_)) => {
                warn!("CAN receive error");
            }
            Either3::Third(()) => {
                // FDCAN "Rx FIFO 0 message lost" (IR.RF0L, RM0440 §44.4.16):
                // frames were dropped because the FIFO was full. The HAL does
                // not report it; the App turns it into EMCY 0x8110. The flag
                // is cleared by writing 1 (other bits written 0 are kept).
                let ir = embassy_stm32::pac::FDCAN1.ir();
                if ir.read().rfl(0) {
                    ir.write(|w| w.set_rfl(0, true));
                    warn!("CAN receive FIFO overrun");
                    app.rx_overrun();
                }
                app.poll(now_us(), &mut push);
                let now = Instant::now();
                match (props.bus_error_mode(), bus_off_since) {
                    (BusErrorMode::BusOff, None) => {
                        warn!("CAN bus-off");
                        bus_off_since = Some(now);
                    }
                    (BusErrorMode::BusOff, Some(_)) => {}
                    (_, Some(_)) => {
                        info!("CAN bus-off recovered");
                        bus_off_since = None;
                        app.bus_off_recovered();
                    }
                    (_, None) => {}
                }
                led.set_level(if led_pattern(app.last_output().status, now.as_millis()) {
                    Level::High
                } else {
                    Level::Low
                });
                let acq_alive = now - last_sample < Duration::from_millis(20);
                let can_alive = bus_off_since.is_none_or(|t| now - t < Duration::from_secs(1));
                if acq_alive && can_alive {
                    wdg.pet();
                }
            }
        }
        if let Some(a) = app.take_acq_change() {
            info!(
                "acquisition: {} µs, 2^{} oversampling",
                a.period_us, a.os_log2
            );
            ring.stop();
            set_oversampling(&a);
            tim.set_frequency(Hertz(1_000_000 / a.period_us), RoundTo::Slower);
            ring.clear();
            ring.start();
            acq = a;
        }
        if let Some(c) = app.take_can_change() {
            if c.bitrate != can_cfg.bitrate {
                warn!(
                    "bit rate {} bit/s takes effect at the next power-on (store it with 0x1010)",
                    c.bitrate.bps()
                );
            }
        }
        while let Some(f) = queue.pop_front() {
            if let Some(hal) = to_hal(&f) {
                // A lower-priority frame displaced from the TX FIFO is
                // dropped; CANopen resends state on the next event.
                let _ = tx.write(&hal).await;
            }
        }
    }
}

//! (Re)starting the acquisition chain TIM3 → ADC1 → DMA1 channel 1 with a
//! new period and oversampling (object 0x2300), or after an overrun.
//!
//! embassy-stm32 0.6's `RingBufferedAdc::stop()` only clears the DMA
//! channel's EN bit; the ADC keeps converting, and its `start()` sets EN and
//! ADSTART again. That leaves three problems this module fixes with PAC
//! calls: CFGR2 (oversampling) may only be written while ADSTART = 0
//! (RM0440 §21.4.30, register notes of ADC_CFGR2), a DMA channel disabled
//! and re-enabled without being reprogrammed is not supported (RM0440
//! §12.4.3 "Channel state and disabling a channel": "suspend and resume"),
//! and a scan interrupted halfway leaves the ring off its scan boundary.
//! The sequence, each step in [`restart`]:
//!
//! 1. stop TIM3 (CR1.CEN = 0, §29.4.1): no more TRGO, no new scan;
//! 2. stop the ADC: ADSTP = 1, wait for ADSTART = 0 (§21.4.17 "Stopping an
//!    ongoing conversion"); the conversion in progress is discarded;
//! 3. stop and reset the DMA ring: CCR.EN = 0 after the ADC stopped
//!    requesting, CNDTR reloaded with the ring length (§12.4.3 "abort and
//!    restart"), the ring's read position back to 0;
//! 4. write CFGR2 (ROVSE, OVSR, OVSS; §21.4.30);
//! 5. clear OVR, EOC, EOS (ADC_ISR, write 1 to clear, §21.7.1);
//! 6. restart: TIM3 period, an update event to load the prescaler (the ADC
//!    is stopped, so its TRGO is ignored), counter 0; DMA EN = 1, ADSTART = 1
//!    (the ADC waits for the trigger, §21.4.18); TIM3 CEN = 1: the first
//!    scan one period later.
//!
//! Acquisition locked to SYNC (0x2301 sub 1 = 1): step 6 leaves TIM3
//! stopped, and each SYNC starts one scan with [`trigger_scan`]: the
//! software update event (EGR.UG, §29.4.11) is an update event, which
//! TIM3's master mode `UPDATE` (CR2.MMS = 010, §29.4.2) puts on TRGO.

use embassy_stm32::adc::{
    Adc, AdcChannel, AdcConfig, AnyAdcChannel, Exten, RingBufferedAdc, SampleTime,
};
use embassy_stm32::dma;
use embassy_stm32::interrupt::typelevel::{Binding, DMA1_CHANNEL1};
use embassy_stm32::pac;
use embassy_stm32::peripherals::{ADC1, DMA1_CH1, TIM3};
use embassy_stm32::timer::low_level::{RoundTo, Timer};
use embassy_stm32::Peri;
use perpend_board::health;
use perpend_core::params::Acquisition;

/// Channels per scan: four sensors, then the temperature sensor.
pub const SCAN: usize = 5;
/// Length of the DMA ring: two scans (half-transfer and transfer-complete
/// interrupts each mark one scan).
pub const RING_LEN: usize = 2 * SCAN;

/// Polls of ADC_CR.ADSTART before giving up (≈ 1 ms at 170 MHz; the stop
/// takes a few ADC clocks).
const ADSTP_SPINS: u32 = 100_000;

/// Restarts the acquisition with `acq` (the steps of the module docs),
/// on the timer or, with `on_sync`, one scan per [`trigger_scan`].
/// Returns `false` if the ADC did not acknowledge the stop (it is then
/// restarted anyway; CFGR2 may have kept its old value).
pub fn restart(
    ring: &mut RingBufferedAdc<'_, ADC1>,
    tim: &Timer<'_, TIM3>,
    acq: &Acquisition,
    on_sync: bool,
) -> bool {
    // 1. No more triggers.
    tim.stop();
    // 2. ADC stopped, no DMA request pending.
    let stopped = stop_adc();
    // 3. DMA channel disabled, reprogrammed, ring position reset.
    ring.stop();
    let ch = pac::DMA1.ch(0);
    for _ in 0..ADSTP_SPINS {
        if !ch.cr().read().en() {
            break;
        }
    }
    ch.ndtr().write(|w| w.set_ndt(RING_LEN as u16));
    ring.clear();
    // 4. Oversampling.
    set_oversampling(acq);
    // 5. Stale flags.
    pac::ADC1.isr().write(|w| {
        w.set_ovr(true);
        w.set_eoc(true);
        w.set_eos(true);
    });
    // 6. Period, then DMA + ADC armed, then the trigger.
    tim.set_period_us(acq.period_us, RoundTo::Slower);
    tim.generate_update_event();
    tim.reset();
    ring.start();
    if !on_sync {
        tim.start();
    }
    stopped
}

/// One scan now (acquisition locked to SYNC): a software update event of
/// the stopped TIM3, whose TRGO starts the ADC sequence.
pub fn trigger_scan(tim: &Timer<'_, TIM3>) {
    tim.generate_update_event();
}

/// Whether the ADC reports an overrun (ISR.OVR, §21.4.27): its DMA requests
/// stop until the flag is cleared, so the chain must be restarted.
pub fn overrun() -> bool {
    pac::ADC1.isr().read().ovr()
}

/// ADSTP and wait for ADSTART = 0; `false` on timeout.
fn stop_adc() -> bool {
    let cr = pac::ADC1.cr();
    let r = cr.read();
    if r.adstart() && !r.addis() {
        cr.modify(|w| w.set_adstp(pac::adc::vals::Adstp::STOP));
    }
    for _ in 0..ADSTP_SPINS {
        if !cr.read().adstart() {
            return true;
        }
    }
    false
}

/// Writes the ADC1 oversampling fields of CFGR2 (ADSTART must be 0).
fn set_oversampling(acq: &Acquisition) {
    let ratio = acq.os_log2.clamp(1, 8) - 1; // OVSR: 0 = 2x .. 7 = 256x
    pac::ADC1.cfgr2().modify(|w| {
        w.set_rovse(acq.os_log2 > 0);
        w.set_ovsr(ratio);
        w.set_ovss(acq.os_shift.min(8));
    });
}

/// Oversampling gain of the scan's results.
pub fn scan_gain(acq: &Acquisition) -> f32 {
    if acq.os_log2 == 0 {
        1.0
    } else {
        health::os_gain(acq.os_log2, acq.os_shift)
    }
}

/// ADC1 with the scan of the board (four inputs, the die temperature) on
/// TIM3's TRGO into a DMA ring; returns the ring and VREF+ measured with
/// VREFINT [mV] (the firmware's and the HIL tests' set-up).
pub fn start(
    adc1: Peri<'static, ADC1>,
    dma: Peri<'static, DMA1_CH1>,
    inputs: [AnyAdcChannel<'static, ADC1>; 4],
    acq: &Acquisition,
    irq: impl Binding<DMA1_CHANNEL1, dma::InterruptHandler<DMA1_CH1>> + 'static,
) -> (RingBufferedAdc<'static, ADC1>, Option<f32>) {
    let mut adc = Adc::new(
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
    // VREF+ from VREFINT (RM0440 §21.4.34), once at boot: 8 conversions
    // averaged, at the scan's oversampling (4 µs minimum sampling time).
    let mut vrefint = adc.enable_vrefint();
    let sum: u32 = (0..8)
        .map(|_| u32::from(adc.blocking_read(&mut vrefint, SampleTime::CYCLES247_5)))
        .sum();
    let (vcal, _, _) = crate::board::factory_cal();
    let vref = health::vref_mv(vcal, (sum / 8) as u16, scan_gain(acq));
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
    let ring = adc.into_ring_buffered(
        dma,
        dma_buf,
        irq,
        seq.into_iter(),
        embassy_stm32::triggers::TIM3_TRGO,
        Exten::RISING_EDGE,
    );
    (ring, vref)
}

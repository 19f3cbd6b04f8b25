//! Tests of `health.rs` (reset causes, supply, stack paint) and of the
//! application's reports of them; kept apart so that `health` (which the
//! application uses) does not import the application.
#![allow(clippy::unwrap_used)]

use crate::health::*;
use proptest::prelude::*;

#[test]
fn reset_causes_from_csr() {
    // power-on: BORRSTF + PINRSTF (RM0440 §7.4.29 reset value 0x0C00_0000)
    assert_eq!(
        ResetFlags::from_csr(0x0C00_0000).cause(),
        ResetCause::PowerOn
    );
    // IWDG also sets the pin flag
    let wd = ResetFlags::from_csr((1 << 29) | (1 << 26));
    assert_eq!(wd.cause(), ResetCause::IndependentWatchdog);
    assert!(wd.is_watchdog());
    assert_eq!(wd.0, 0x24);
    assert_eq!(
        ResetFlags::from_csr((1 << 28) | (1 << 26)).cause(),
        ResetCause::Software
    );
    assert!(!ResetFlags::from_csr(1 << 28).is_watchdog());
    assert_eq!(ResetFlags::from_csr(1 << 26).cause(), ResetCause::Pin);
    assert_eq!(
        ResetFlags::from_csr(1 << 30).cause(),
        ResetCause::WindowWatchdog
    );
    assert_eq!(ResetFlags::from_csr(1 << 31).cause(), ResetCause::LowPower);
    assert_eq!(
        ResetFlags::from_csr(1 << 25).cause(),
        ResetCause::OptionLoad
    );
    // other CSR bits (LSION, RMVF) do not count
    assert_eq!(
        ResetFlags::from_csr(0x0080_0001).cause(),
        ResetCause::Unknown
    );
}

#[test]
fn vref_from_vrefint() {
    // a typical VREFINT_CAL of 1655 counts (1.212 V at 3.0 V)
    let cal = 1655;
    // at VREF+ = 3.3 V the reading is 1655·3.0/3.3 = 1504.5; 16×
    // oversampling without shift: ×16
    let v = vref_mv(cal, (1504.5f32 * 16.0) as u16, os_gain(4, 0)).unwrap();
    assert!((v - 3300.0).abs() < 0.5, "{v}");
    // at 3.0 V exactly the calibration value
    assert_eq!(vref_mv(cal, cal, 1.0), Some(3000.0));
    // implausible: no calibration, 0 reading, VREF+ > 3.6 V
    assert_eq!(vref_mv(0, 1500, 1.0), None);
    assert_eq!(vref_mv(cal, 0, 1.0), None);
    assert_eq!(vref_mv(cal, 1300, 1.0), None);
}

#[test]
fn count_correction_and_its_size() {
    // VREF+ 1 % low (3.267 V): a count read at 3.267 V is 1 % too
    // high for 3.3 V; the corrected one is 1 % lower.
    let c = correct_count(40_000, 3267.0, 3300.0);
    assert_eq!(c, 39_600);
    assert_eq!(correct_count(65_535, 3600.0, 3300.0), u16::MAX);
    assert_eq!(correct_count(1234, 3300.0, 0.0), 1234);
}

#[test]
fn die_temperature_at_the_calibration_points() {
    let (c1, c2) = (1034, 1375);
    let t = |raw: u16, g: f32, v: f32| die_temp_c(raw, g, v, c1, c2).unwrap();
    assert!((t(c1, 1.0, 3000.0) - 30.0).abs() < 1e-4);
    assert!((t(c2, 1.0, 3000.0) - 130.0).abs() < 1e-4);
    // the same 30 °C read at 3.3 V with 16× oversampling
    let raw = (c1 as f32 * 3000.0 / 3300.0 * 16.0).round() as u16;
    assert!((t(raw, 16.0, 3300.0) - 30.0).abs() < 0.05);
    assert_eq!(die_temp_c(1000, 1.0, 3000.0, c2, c1), None);
}

#[test]
fn flash_layout() {
    assert_eq!(check_flash(true, 512, 512), Ok(()));
    assert_eq!(check_flash(false, 512, 512), Err(HealthError::SingleBank));
    assert_eq!(
        check_flash(true, 256, 512),
        Err(HealthError::FlashTooSmall(256))
    );
}

#[test]
fn loop_timer_keeps_the_worst_across_a_wrap() {
    let mut l = LoopTimer::default();
    assert!(l.record(100, 1100));
    assert!(!l.record(5000, 5500));
    assert!(l.record(u32::MAX - 99, 2000)); // wrapped: 2100 cycles
    assert_eq!(l.worst(), 2100);
}

fn booted() -> crate::app::App<crate::storage::SeqStore<crate::storage::HostFlash>> {
    let mut app =
        crate::app::App::new(crate::storage::host_store(crate::storage::HostFlash::new()));
    app.poll(0, &mut |_| {});
    app
}

fn emcy_codes(frames: &[perpend_can::Frame]) -> std::vec::Vec<u16> {
    frames
        .iter()
        .filter(|f| (0x81..=0xFF).contains(&f.id))
        .map(|f| u16::from_le_bytes([f.data[0], f.data[1]]))
        .collect()
}

#[test]
fn a_watchdog_reset_is_reported_by_object_and_emcy() {
    let mut app = booted();
    let flags = ResetFlags::from_csr((1 << 29) | (1 << 26));
    app.report_reset(flags);
    let mut out = std::vec::Vec::new();
    app.poll(1000, &mut |f| out.push(f));
    assert_eq!(emcy_codes(&out), [EMCY_WATCHDOG_RESET, 0]);
    let e = out.iter().find(|f| f.data[..2] == [0x10, 0x60]).unwrap();
    assert_eq!(e.data[3], 0x24);
    assert_eq!(app.device().read_u32(0x200B, 1), Some(0x24));
    // a power-on reset: the object only
    let mut app = booted();
    app.report_reset(ResetFlags::from_csr(0x0C00_0000));
    let mut out = std::vec::Vec::new();
    app.poll(1000, &mut |f| out.push(f));
    assert_eq!(emcy_codes(&out), std::vec::Vec::<u16>::new());
    assert_eq!(app.device().read_u32(0x200B, 1), Some(0x0C));
}

#[test]
fn die_temperature_and_health_reach_the_dictionary() {
    let mut app = booted();
    let unknown = perpend_can::od::DIE_TEMP_UNKNOWN;
    assert_eq!(app.device().read_f32(0x200A, 0), Some(unknown));
    let s = crate::pipeline::Sample {
        temp_c: Some(41.5),
        ..Default::default()
    };
    app.on_sample(&s, 1000);
    app.poll(2000, &mut |_| {});
    assert_eq!(app.device().read_f32(0x200A, 0), Some(41.5));
    // a sample without temperature keeps the last value
    app.on_sample(&crate::pipeline::Sample::default(), 3000);
    app.poll(4000, &mut |_| {});
    assert_eq!(app.device().read_f32(0x200A, 0), Some(41.5));
    app.set_health(123_456, 2048, 3297);
    let h: std::vec::Vec<_> = (2..=4).map(|s| app.device().read_u32(0x200B, s)).collect();
    assert_eq!(h, [Some(123_456), Some(2048), Some(3297)]);
}

#[test]
fn the_bootloader_command_is_honoured_in_pre_operational_only() {
    let sdo = |app: &mut crate::app::App<_>, v: u8| {
        let f = perpend_can::Frame::new(0x620, &[0x2F, 0x00, 0x25, 0, v, 0, 0, 0]);
        let mut out = std::vec::Vec::new();
        app.handle(&f, 100, &mut |o| out.push(o));
        out.iter().find(|o| o.id == 0x5A0).map(|o| o.data[0])
    };
    let mut app = booted();
    assert_eq!(sdo(&mut app, perpend_can::od::CMD_BOOTLOADER), Some(0x60));
    assert!(app.take_bootloader_request());
    assert!(!app.take_bootloader_request());
    // operational: written (it is the command object) but not honoured
    app.handle(&perpend_can::Frame::new(0, &[1, 0x20]), 200, &mut |_| {});
    assert_eq!(app.device().nmt_state(), perpend_can::NmtState::Operational);
    assert_eq!(sdo(&mut app, perpend_can::od::CMD_BOOTLOADER), Some(0x60));
    assert!(!app.take_bootloader_request());
    // other values are refused as before
    assert_eq!(sdo(&mut app, 0xB1), Some(0x80));
}

#[test]
fn a_release_bootloader_refuses_the_rom_loader_command_with_an_abort() {
    let sdo = |app: &mut crate::app::App<_>, v: u8| {
        let f = perpend_can::Frame::new(0x620, &[0x2F, 0x00, 0x25, 0, v, 0, 0, 0]);
        let mut out = std::vec::Vec::new();
        app.handle(&f, 100, &mut |o| out.push(o));
        out.iter().find(|o| o.id == 0x5A0).map(|o| o.data)
    };
    let mut app = booted();
    app.set_rom_loader_policy(crate::bootctl::RomLoaderPolicy::default());
    let r = sdo(&mut app, perpend_can::od::CMD_BOOTLOADER).unwrap();
    assert_eq!(r[0], 0x80);
    assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), 0x0800_0022);
    assert!(!app.take_bootloader_request(), "nothing resets");
    // provisioned: allowed again
    app.set_rom_loader_policy(crate::bootctl::RomLoaderPolicy {
        test_key: false,
        provisioned: true,
    });
    assert_eq!(
        sdo(&mut app, perpend_can::od::CMD_BOOTLOADER).unwrap()[0],
        0x60
    );
    assert!(app.take_bootloader_request());
}

#[test]
fn wrong_option_bytes_raise_an_emcy_that_stays() {
    let mut app = booted();
    app.report_option_bytes(0xFFEF_F8AA);
    assert!(!app.device().emcy_active(crate::bootctl::EMCY_OPTION_BYTES));
    app.report_option_bytes(0xFFEF_F8AA & !crate::bootctl::OPTR_DBANK);
    assert!(app.device().emcy_active(crate::bootctl::EMCY_OPTION_BYTES));
    for t in 0..200u64 {
        app.on_sample(&crate::pipeline::Sample::default(), t * 1000);
    }
    assert!(app.device().emcy_active(crate::bootctl::EMCY_OPTION_BYTES));
}

proptest! {
    #[test]
    fn stack_used_counts_the_touched_top(len in 1usize..64, used in 0usize..64) {
        let used = used.min(len);
        let mut w = vec![STACK_PAINT; len];
        for x in w.iter_mut().skip(len - used) {
            *x = 0x1234_5678;
        }
        prop_assert_eq!(stack_used(w.iter().copied()), used * 4);
    }
}

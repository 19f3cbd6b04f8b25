//! Power cuts with ECC errors (issue 11 item 4): a [`FaultFlash`] that
//! makes the torn double word of a cut store unreadable (as the STM32G4's
//! ECC double error), read through the board's [`EccGuard`]: at every cut
//! position of a store the next boot loads the old record, the new one or
//! factory defaults, without an error, and the boot after that too (the
//! board can never boot-loop); the application raises EMCY 0x6300 with the
//! fault count; a store with low supply writes nothing.

use crate::app::{App, EMCY_LOW_SUPPLY};
use crate::storage::*;
use embassy_futures::block_on;
use embedded_storage_async::nor_flash::ReadNorFlash;
use perpend_core::params::{Params, Transfer};

fn params(k: u32) -> Params {
    let mut p = Params::factory();
    p.stamp = 1000 + k;
    p.head.sensors[k as usize % 4].zero.x += 0.001 * k as f32;
    p.transfer[1] = Transfer::voltage(0.3, 10.0, 60.0 + k as f32);
    p
}

fn tail(k: u32, len: usize) -> Vec<u8> {
    (0..len).map(|i| (i as u32 * 7 + k) as u8).collect()
}

/// Outcome counts of one sweep: (cuts, boots that met ECC words, loaded
/// old, loaded new, factory).
#[derive(Debug, Default)]
struct Sweep {
    cuts: u32,
    ecc_boots: u32,
    old: u32,
    new: u32,
    factory: u32,
}

/// `before` stores, then a store cut at every step; each cut flash is
/// booted twice through the ECC guard and then stored to again.
fn sweep(before: u32, tail_len: usize, s: &mut Sweep) {
    let mut st = ecc_host_store(HostFlash::new().with_ecc());
    for k in 0..before {
        save_with_tail(&mut st, &params(k), &tail(k, tail_len)).unwrap();
    }
    let base = st.into_flash().into_inner();
    let mut probe = ecc_host_store(base.clone());
    save_with_tail(&mut probe, &params(before), &tail(before, tail_len)).unwrap();
    let total = probe.into_flash().into_inner().steps() - base.steps();
    let mut got = [0u8; MAX_ITEM];
    for cut in 0..total {
        let mut f = base.clone();
        f.cut_power_after(cut);
        let mut st = ecc_host_store(f);
        let r = save_with_tail(&mut st, &params(before), &tail(before, tail_len));
        assert_eq!(r, Err(SaveError::Store(StoreError::Flash)), "cut {cut}");
        let mut f = st.into_flash().into_inner();
        f.power_on();
        // Two boots in a row: the same answer, never an error.
        let mut answers = Vec::new();
        for _ in 0..2 {
            let mut st = ecc_host_store(f.clone());
            let (p, boot, n) = load_with_tail(&mut st, &mut got);
            let faults = st.take_read_faults();
            let ctx = format!("before {before} cut {cut}/{total}: {boot:?}, {faults} ECC");
            assert!(matches!(boot, Boot::Stored | Boot::Missing), "{ctx}");
            if p == params(before) {
                assert_eq!(&got[..n], &tail(before, tail_len)[..], "{ctx}");
            } else if before > 0 {
                assert_eq!(p, params(before - 1), "{ctx}");
                assert_eq!(&got[..n], &tail(before - 1, tail_len)[..], "{ctx}");
            } else {
                assert_eq!(p, Params::factory(), "{ctx}");
            }
            answers.push((p, boot, faults));
        }
        assert_eq!(answers[0], answers[1], "cut {cut}: second boot differs");
        let (p, _, faults) = answers[0];
        s.cuts += 1;
        s.ecc_boots += u32::from(faults > 0);
        if p == params(before) {
            s.new += 1;
        } else if p == Params::factory() {
            s.factory += 1;
        } else {
            s.old += 1;
        }
        // The storage is usable: a store over the unreadable word works
        // and the boot after it loads it.
        let mut st = ecc_host_store(f);
        let _ = load_with_tail(&mut st, &mut got);
        save(&mut st, &params(99)).unwrap();
        let mut st = ecc_host_store(st.into_flash().into_inner());
        assert_eq!(load(&mut st), (params(99), Boot::Stored), "cut {cut}");
    }
}

#[test]
fn ecc_error_at_every_cut_position_never_stops_the_boot() {
    let mut s = Sweep::default();
    for before in 0..12 {
        sweep(before, 0, &mut s);
    }
    // and with the board's device image after the record
    for before in 0..6 {
        sweep(before, perpend_can::device::IMAGE_LEN, &mut s);
    }
    // Every cut of a program step leaves an unreadable word that the boot
    // reads (the items are scanned), so most boots meet one.
    assert!(s.cuts > 1000, "{s:?}");
    assert!(s.ecc_boots * 2 > s.cuts, "{s:?}");
    assert!(s.old > 0 && s.factory > 0, "{s:?}");
    eprintln!("{s:?}");
}

#[test]
fn without_the_guard_an_ecc_word_is_a_read_error() {
    // What the guard prevents: the raw driver's error reaches the map and
    // the boot would see "unreadable" (on the board: the NMI loop).
    let mut f = HostFlash::new().with_ecc();
    f.cut_power_after(3);
    let mut st = host_store(f);
    assert!(save(&mut st, &params(1)).is_err());
    let mut f = st.into_flash();
    f.power_on();
    assert_eq!(f.bad_words().len(), 1);
    let at = f.bad_words()[0];
    let mut b = [0u8; 16];
    assert_eq!(block_on(f.read(at, &mut b)), Err(FlashFault::Ecc(at)));
    // Through the guard the same read succeeds with the fill pattern.
    let mut g = EccGuard::new(f);
    block_on(g.read(at, &mut b)).unwrap();
    assert_eq!(&b[..8], &[ECC_FILL; 8]);
    assert_eq!((g.last_fault(), g.take_read_faults()), (Some(at), 1));
    assert_eq!(g.take_read_faults(), 0);
}

/// Sends 0x1010 sub 1 "save" to the board and returns its frames.
fn sdo_save(app: &mut App<SeqStore<EccHostFlash>>, now_us: u64) -> Vec<perpend_can::Frame> {
    let save = 0x6576_6173u32.to_le_bytes();
    let req = perpend_can::Frame::new(
        0x620,
        &[0x23, 0x10, 0x10, 1, save[0], save[1], save[2], save[3]],
    );
    let mut out = Vec::new();
    app.poll(now_us, &mut |f| out.push(f));
    app.handle(&req, now_us + 100, &mut |f| out.push(f));
    app.poll(now_us + 1000, &mut |f| out.push(f));
    out
}

#[test]
fn app_boot_over_an_ecc_word_raises_data_set_emcy_with_the_count() {
    let mut app = App::new(ecc_host_store(HostFlash::new().with_ecc()));
    sdo_save(&mut app, 0);
    assert_eq!(app.stores(), 1);
    let mut f = app.into_store().into_flash().into_inner();
    let steps = f.steps();
    // Cut the second store in its data (the first store's step count in,
    // so inside the item), at every tenth step.
    let mut seen = 0;
    for cut in (2..steps).step_by(10) {
        let mut g = f.clone();
        g.cut_power_after(cut);
        let mut app = App::new(ecc_host_store(g));
        sdo_save(&mut app, 0);
        let mut g = app.into_store().into_flash().into_inner();
        g.power_on();
        let bad = g.bad_words().len() as u32;
        assert_eq!(bad, 1, "cut {cut}");
        let mut app = App::new(ecc_host_store(g));
        // The first record is still there; the torn one was skipped.
        assert_eq!(app.boot(), Boot::Stored, "cut {cut}");
        let faults = app.boot_read_faults();
        let mut frames = Vec::new();
        // the boot-up, then (a poll later) what the boot raised
        app.poll(0, &mut |f| frames.push(f));
        app.poll(100, &mut |f| frames.push(f));
        let emcy = frames.iter().find(|f| f.id == 0xA0);
        if faults == 0 {
            assert!(emcy.is_none(), "cut {cut}");
            continue;
        }
        seen += 1;
        let emcy = emcy.expect("an EMCY frame");
        assert_eq!(&emcy.data[..2], &0x6300u16.to_le_bytes());
        let mut d = [1u8, 0, 0, 0, 0];
        d[1..].copy_from_slice(&faults.to_le_bytes());
        assert_eq!(&emcy.data[3..8], &d, "cut {cut}");
    }
    assert!(seen > 0);
    f.power_on();
}

#[test]
fn low_supply_refuses_the_store_and_writes_nothing() {
    let mut f = HostFlash::new();
    f.set_low_supply(true);
    let mut st = ecc_host_store(f);
    assert_eq!(
        save(&mut st, &params(1)),
        Err(SaveError::Store(StoreError::LowSupply))
    );
    let mut f = st.into_flash().into_inner();
    assert_eq!(f.steps(), 0);
    f.set_low_supply(false);
    let mut st = ecc_host_store(f);
    save(&mut st, &params(1)).unwrap();
    assert_eq!(load(&mut st), (params(1), Boot::Stored));
}

#[test]
fn app_refuses_a_store_with_low_supply_with_abort_and_emcy() {
    let mut f = HostFlash::new();
    f.set_low_supply(true);
    let mut app = App::new(ecc_host_store(f));
    let out = sdo_save(&mut app, 0);
    let abort = out.iter().find(|f| f.id == 0x5A0).expect("an SDO answer");
    assert_eq!(abort.data[0], 0x80);
    assert_eq!(&abort.data[4..8], &0x0800_0020u32.to_le_bytes());
    let codes: Vec<u16> = out
        .iter()
        .filter(|f| f.id == 0xA0)
        .map(|f| u16::from_le_bytes([f.data[0], f.data[1]]))
        .collect();
    assert_eq!(codes, [EMCY_LOW_SUPPLY, 0x0000]);
    assert_eq!(app.stores(), 0);
    assert_eq!(app.into_store().into_flash().into_inner().steps(), 0);
}

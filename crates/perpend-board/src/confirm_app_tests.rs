//! The application's boot confirmation (`confirm.rs` wired into `App`):
//! kept apart from `confirm.rs` so that it, which the application uses,
//! does not import the application.
#![allow(clippy::unwrap_used)]

use crate::app::App;
use crate::image;
use crate::program::{BootState, ProgramStore, RamProgram};
use crate::storage::{host_store, HostFlash};
use perpend_can::Frame;

/// An App whose store holds v2 on trial (v1 confirmed before).
fn app_on_trial() -> App<crate::storage::SeqStore<HostFlash>, RamProgram> {
    let mut p = RamProgram::new(8192);
    p.active_image = image::sign(&[1; 300], 7, image::version(1, 0, 0), &image::TEST_SEED);
    p.image = image::sign(&[2; 400], 7, image::version(2, 0, 0), &image::TEST_SEED);
    p.mark_updated().unwrap();
    p.reset();
    App::with_program(host_store(HostFlash::new()), 3, p)
}

#[test]
fn the_app_confirms_after_can_and_its_first_heartbeat_only() {
    let mut app = app_on_trial();
    let mut sent = Vec::new();
    // Boot-up message only (0x700 + node, state 0); no heartbeat yet.
    app.poll(0, &mut |f: Frame| sent.push((f.id, f.data[0])));
    let hb = 0x700 + u16::from(app.device().node_id());
    assert_eq!(sent, vec![(hb, 0)], "the boot-up message");
    assert_eq!(app.confirm_boot(true), None, "the boot-up is no heartbeat");
    assert_eq!(app.program_mut().boot, BootState::Trial);
    let beat = |s: &Vec<(u16, u8)>| s.iter().any(|&(id, st)| id == hb && st != 0);
    let mut t = 0;
    while !beat(&sent) && t < 5_000_000 {
        t += 1000;
        app.poll(t, &mut |f: Frame| sent.push((f.id, f.data[0])));
    }
    assert!(beat(&sent), "no heartbeat within 5 s: {sent:x?}");
    // CAN was reported running before: it stays so.
    assert_eq!(app.confirm_boot(false), Some(Ok(())));
    assert_eq!(app.program_mut().boot, BootState::Boot);
    assert_eq!(app.confirm_boot(true), None, "once");
}

#[test]
fn the_app_confirms_after_a_sync_it_answered() {
    let mut app = app_on_trial();
    app.poll(0, &mut |_| {});
    // Operational (the device started directly, so that the NMT command
    // itself, which serves too, is not seen): a SYNC is answered with the
    // TPDOs.
    let start = Frame::new(0x000, &[0x01, 0]);
    app.device_mut().handle(&start, 100, &mut |_| {});
    assert_eq!(app.device().nmt_state(), perpend_can::NmtState::Operational);
    assert_eq!(app.confirm_boot(true), None);
    let mut answered = 0;
    app.handle(&Frame::new(0x080, &[]), 200, &mut |_| answered += 1);
    assert!(answered > 0, "the SYNC was not answered");
    assert_eq!(app.confirm_boot(true), Some(Ok(())));
    assert_eq!(app.program_mut().boot, BootState::Boot);
}

/// One SDO request to node 0x20; the answer's first frame.
fn sdo(app: &mut App<crate::storage::SeqStore<HostFlash>, RamProgram>, req: [u8; 8]) -> [u8; 8] {
    let mut out = Vec::new();
    let id = 0x600 + u16::from(app.device().node_id());
    app.handle(&Frame::new(id, &req), 0, &mut |f: Frame| out.push(f.data));
    out[0]
}

#[test]
fn start_of_a_verified_image_asks_once_for_the_restart() {
    let mut app = app_on_trial();
    app.poll(0, &mut |_| {});
    app.program_mut().mark_booted().unwrap();
    let product = app.device().defaults().identity.product_code;
    let img = image::sign(
        &[5; 200],
        product,
        image::version(3, 0, 0),
        &image::TEST_SEED,
    );
    let l = (img.len() as u32).to_le_bytes();
    sdo(&mut app, [0x21, 0x50, 0x1F, 1, l[0], l[1], l[2], l[3]]);
    let mut t = 0u8;
    for (k, c) in img.chunks(7).enumerate() {
        let mut f = [0u8; 8];
        let last = u8::from((k + 1) * 7 >= img.len());
        f[0] = t | (((7 - c.len()) as u8) << 1) | last;
        f[1..=c.len()].copy_from_slice(c);
        assert_eq!(sdo(&mut app, f)[0] & 0xE0, 0x20, "segment {k}");
        t ^= 0x10;
    }
    assert!(!app.take_update_restart(), "downloaded, not started");
    assert_eq!(sdo(&mut app, [0x2F, 0x51, 0x1F, 1, 1, 0, 0, 0])[0], 0x60);
    assert_eq!(app.program_mut().boot, BootState::SwapPending);
    assert!(app.take_update_restart());
    assert!(!app.take_update_restart(), "once");
}

/// Runs `app` from `from` to `to` µs in 1 ms polls; frames dropped.
fn run(app: &mut App<crate::storage::SeqStore<HostFlash>, RamProgram>, from: u64, to: u64) {
    let mut t = from;
    while t < to {
        app.poll(t, &mut |_| {});
        t += 1000;
    }
}

#[test]
fn an_image_that_rejects_the_stored_record_never_confirms_and_is_reverted() {
    // issue 50 item 3: "storage loaded" was set whatever the boot found
    let mut store = host_store(HostFlash::new());
    let mut bad = [0u8; perpend_core::params::RECORD_LEN];
    perpend_core::params::Params::factory()
        .encode(&mut bad)
        .unwrap();
    bad[4] = 9; // a record version this image does not know
    crate::storage::ParamStore::store(&mut store, &bad).unwrap();
    let mut p = RamProgram::new(8192);
    let v1 = image::sign(&[1; 300], 7, image::version(1, 0, 0), &image::TEST_SEED);
    p.active_image = v1.clone();
    p.image = image::sign(&[2; 400], 7, image::version(2, 0, 0), &image::TEST_SEED);
    p.mark_updated().unwrap();
    p.reset();
    let mut app = App::with_program(store, 3, p);
    assert!(matches!(app.boot(), crate::storage::Boot::Rejected(_)));
    assert!(app.on_trial());
    run(&mut app, 0, 5_000_000); // heartbeats sent
    app.handle(&Frame::new(0x000, &[0x01, 0]), 5_000_000, &mut |_| {});
    assert_eq!(
        app.confirm_boot(true),
        None,
        "a rejected record is not loaded"
    );
    assert!(!app.trial_expired(5_000_000));
    assert!(app.trial_expired(crate::confirm::TRIAL_DEADLINE_US));
    // the firmware resets: the bootloader swaps v1 back
    assert_eq!(app.program_mut().reset(), BootState::Boot);
    assert_eq!(app.program_mut().active_image, v1);
}

#[test]
fn an_image_whose_frames_are_never_acknowledged_is_reset_at_the_deadline() {
    // issue 50 item 3: no deadline, it ran unconfirmed until a power cycle
    let mut app = app_on_trial();
    run(&mut app, 0, crate::confirm::TRIAL_DEADLINE_US - 1000);
    assert_eq!(app.confirm_boot(false), None, "no frame acknowledged");
    assert!(!app.trial_expired(crate::confirm::TRIAL_DEADLINE_US - 1000));
    assert!(app.trial_expired(crate::confirm::TRIAL_DEADLINE_US));
    assert!(
        !app.trial_expired(crate::confirm::TRIAL_DEADLINE_US + 1000),
        "once"
    );
    assert_eq!(app.confirm_boot(true), None, "no late confirmation");
}

#[test]
fn a_board_not_on_trial_never_expires() {
    let mut app = App::with_program(host_store(HostFlash::new()), 3, RamProgram::new(8192));
    assert!(!app.on_trial());
    assert!(!app.trial_expired(10 * crate::confirm::TRIAL_DEADLINE_US));
}

/// Heartbeat producer off (0x1017 = 0) in the stored image, no SYNC.
fn app_on_trial_without_heartbeat() -> App<crate::storage::SeqStore<HostFlash>, RamProgram> {
    let mut app = App::with_program(host_store(HostFlash::new()), 3, RamProgram::new(8192));
    app.poll(0, &mut |_| {});
    let hb0 = [0x2B, 0x17, 0x10, 0, 0, 0, 0, 0];
    assert_eq!(sdo(&mut app, hb0)[0], 0x60);
    let save = u32::from_le_bytes(*b"save").to_le_bytes();
    assert_eq!(
        sdo(
            &mut app,
            [0x23, 0x10, 0x10, 1, save[0], save[1], save[2], save[3]]
        )[0],
        0x60
    );
    let store = app.into_store();
    let mut p = RamProgram::new(8192);
    p.active_image = image::sign(&[1; 300], 7, image::version(1, 0, 0), &image::TEST_SEED);
    p.image = image::sign(&[2; 400], 7, image::version(2, 0, 0), &image::TEST_SEED);
    p.mark_updated().unwrap();
    p.reset();
    let app = App::with_program(store, 3, p);
    assert_eq!(app.boot(), crate::storage::Boot::Stored);
    assert_eq!(app.device().read_u32(0x1017, 0), Some(0));
    app
}

#[test]
fn a_master_without_heartbeat_or_sync_confirms_by_nmt_start() {
    // issue 50 item 3: with the heartbeat off and no SYNC the image was
    // never confirmed and reverted
    let mut app = app_on_trial_without_heartbeat();
    run(&mut app, 0, 10_000_000);
    assert_eq!(app.confirm_boot(true), None, "nothing served yet");
    app.handle(&Frame::new(0x000, &[0x01, 0]), 10_000_000, &mut |_| {});
    assert_eq!(app.confirm_boot(true), Some(Ok(())));
    assert_eq!(app.program_mut().boot, BootState::Boot);
    assert!(!app.trial_expired(crate::confirm::TRIAL_DEADLINE_US));
}

#[test]
fn a_master_without_heartbeat_or_sync_confirms_by_an_sdo_request() {
    let mut app = app_on_trial_without_heartbeat();
    run(&mut app, 0, 1_000_000);
    assert_eq!(sdo(&mut app, [0x40, 0x00, 0x10, 0, 0, 0, 0, 0])[0], 0x43);
    assert_eq!(app.confirm_boot(true), Some(Ok(())));
    // an NMT command for another node does not count
    let mut other = app_on_trial_without_heartbeat();
    other.handle(&Frame::new(0x000, &[0x01, 0x7F]), 100, &mut |_| {});
    assert_eq!(other.confirm_boot(true), None);
}

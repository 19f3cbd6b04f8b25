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
    // Operational: a SYNC is answered with the TPDOs.
    let start = Frame::new(0x000, &[0x01, 0]);
    app.handle(&start, 100, &mut |_| {});
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

//! Tests of [`FdcanTx`] against a fake FDCAN whose cancellation can stay
//! outstanding and whose CCE resets the transmit state as the M_CAN core.

use super::*;
use crate::txq::TxQueue;

const NBTP_250K: u32 = 0x0203_0A03;

#[path = "fdcan_fake.rs"]
mod fake;
use fake::Fake;

fn fr(id: u16) -> Frame {
    Frame::new(id, &id.to_le_bytes())
}

/// Three buffers full (0x300..0x302), then 0x100 offered: the cancellation
/// of 0x302 is requested and held outstanding.
fn cancelling() -> FdcanTx<Fake> {
    let mut tx = FdcanTx::new(Fake {
        hold_cancel: true,
        ring_room: 8,
        ..Fake::default()
    });
    for id in [0x300, 0x301, 0x302] {
        assert_eq!(tx.try_write(&fr(id)), TryWrite::Accepted);
    }
    assert_eq!(tx.try_write(&fr(0x100)), TryWrite::Full);
    assert!(tx.is_cancelling());
    tx
}

/// Runs `ticks` bus ticks, each followed by a queue service.
fn run(tx: &mut FdcanTx<Fake>, q: &mut TxQueue<8>, ticks: usize) {
    for _ in 0..ticks {
        tx.regs_mut().tick();
        q.service(tx);
    }
}

#[test]
fn old_switch_with_cancellation_outstanding_stalls_forever() {
    let mut tx = cancelling();
    // The old switch: INIT, CCE, NBTP, and nothing else.
    tx.regs_mut().enter_init();
    tx.regs_mut().program_nbtp(NBTP_250K);
    tx.regs_mut().hold_cancel = false;
    let mut q = TxQueue::<8>::new();
    q.push(fr(0x100));
    q.push(fr(0x700));
    run(&mut tx, &mut q, 50);
    assert!(tx.regs_mut().sent.is_empty(), "the old switch sent frames");
    assert_eq!(
        q.len(),
        2,
        "frames left the queue although TXBCF never came"
    );
}

#[test]
fn switch_with_cancellation_outstanding_requeues_and_sends() {
    let mut tx = cancelling();
    let sw = tx.switch_bitrate(NBTP_250K);
    assert!(!tx.is_cancelling());
    assert_eq!(tx.regs_mut().nbtp, NBTP_250K);
    let mut ids: std::vec::Vec<u16> = sw.requeue.iter().map(|f| f.id).collect();
    ids.sort_unstable();
    assert_eq!(ids, [0x300, 0x301, 0x302]);
    // TXBCF never comes for the forgotten cancellation: still no stall.
    let mut q = TxQueue::<8>::new();
    q.push(fr(0x100));
    q.push(fr(0x700));
    for f in &sw.requeue {
        q.push(*f);
    }
    run(&mut tx, &mut q, 20);
    let sent: std::vec::Vec<u16> = tx.regs_mut().sent.iter().map(|f| f.id).collect();
    assert_eq!(sent, [0x100, 0x300, 0x301, 0x302, 0x700]);
    assert!(q.is_empty());
}

#[test]
fn switch_after_a_finished_unresolved_cancellation_requeues_it_once() {
    let mut tx = cancelling();
    tx.regs_mut().hold_cancel = false;
    // The cancellation finishes on the bus, the firmware has not seen it
    // yet; 0x300 is sent meanwhile.
    tx.regs_mut().tick();
    let sw = tx.switch_bitrate(NBTP_250K);
    let mut ids: std::vec::Vec<u16> = sw.requeue.iter().map(|f| f.id).collect();
    ids.sort_unstable();
    assert_eq!(ids, [0x301, 0x302]);
    assert_eq!(tx.regs_mut().sent.len(), 1);
}

#[test]
fn switch_counts_received_frames_the_ring_cannot_take() {
    let mut tx = FdcanTx::new(Fake {
        rx_fifo: 5,
        ring_room: 2,
        ..Fake::default()
    });
    let sw = tx.switch_bitrate(NBTP_250K);
    assert_eq!(sw.rx_lost, 3);
    assert_eq!(tx.regs_mut().ring, 2);
    assert!(sw.requeue.is_empty());
}

#[test]
fn finished_cancellation_displaces_the_lowest_priority_frame() {
    let mut tx = cancelling();
    // The cancellation completes, no frame is sent meanwhile.
    let f = tx.regs_mut();
    f.bcf |= f.cancel_req & f.brp;
    f.brp &= !f.cancel_req;
    f.cancel_req = 0;
    let r = tx.try_write(&fr(0x100));
    assert_eq!(r, TryWrite::Displaced(fr(0x302)));
    assert!(!tx.is_cancelling());
}

//! The board's logic tested as compiled for the board (issue 33 item 4):
//! perpend-core, perpend-board and perpend-can built for
//! thumbv7em-none-eabihf in `f32` with the firmware's release profile and
//! run by `cargo xtask hil --qemu` on QEMU `mps2-an386` (Cortex-M4F).
//!
//! No STM32 peripheral is touched: the FDCAN, flash and ECC logic runs
//! against fakes of their registers (the traits of `perpend_board::fdcan`
//! and `perpend_board::ecc`, the `FaultFlash` of `perpend_board::storage`).
//! The peripherals themselves are tested on a board by `cargo xtask hil`
//! (`hil/`).
//!
//! Each test prints `test NAME ... ok` or `test NAME ... FAILED: why`
//! through semihosting; the program exits with status 0 only when every
//! test passed (xtask turns any other status into a CI failure).

#![no_std]
#![no_main]

mod fakes;
/// perpend-board's FDCAN fake, the one its host tests use.
#[path = "../../../crates/perpend-board/src/fdcan_fake.rs"]
mod fdcan_fake;

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};
use fakes::FakeEcc;
use fdcan_fake::Fake as FakeFdcan;
use nalgebra::Vector3;
use perpend_board::app::App;
use perpend_board::busmon::{BusEvent, BusMonitor};
use perpend_board::ecc::guarded_read;
use perpend_board::fdcan::{FdcanRegs, FdcanTx, BUFFERS};
use perpend_board::pipeline::{Pipeline, Sample};
use perpend_board::rxfilter::{accepts, filters, Fifo, RxSet};
use perpend_board::storage::{host_store, load, save, Boot, FaultFlash, SeqStore};
use perpend_board::txq::TxQueue;
use perpend_can::Frame;
use perpend_core::geometry::Plane;
use perpend_core::model::distance;
use perpend_core::params::Params;

/// A test: `Err` names what went wrong.
type Outcome = Result<(), &'static str>;

/// A test and its name.
type Test = (&'static str, fn() -> Outcome);

/// Every test, by name.
const TESTS: &[Test] = &[
    ("normal_of_tilted_planes_f32", normal_of_tilted_planes_f32),
    (
        "fdcan_switch_with_cancel_outstanding",
        fdcan_switch_with_cancel_outstanding,
    ),
    ("txq_priority_through_fdcan", txq_priority_through_fdcan),
    ("rxfilter_default_set", rxfilter_default_set),
    (
        "busmon_counts_lec_and_bus_off",
        busmon_counts_lec_and_bus_off,
    ),
    (
        "ecc_read_substitutes_double_errors",
        ecc_read_substitutes_double_errors,
    ),
    ("storage_cut_at_each_step", storage_cut_at_each_step),
    ("sdo_upload_device_type", sdo_upload_device_type),
    ("emcy_on_sensor_fault", emcy_on_sensor_fault),
];

/// Largest angle between the pipeline's normal and the true plane's
/// [rad]: 0.05°, ADC quantisation of the synthetic counts included.
const NORMAL_TOL_RAD: f32 = 0.05 * core::f32::consts::PI / 180.0;

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    hprintln!("panic: {}", info);
    debug::exit(debug::EXIT_FAILURE);
    cortex_m::asm::udf()
}

#[entry]
fn main() -> ! {
    let mut failed = 0u32;
    for (name, test) in TESTS {
        match test() {
            Ok(()) => hprintln!("test {} ... ok", name),
            Err(why) => {
                failed += 1;
                hprintln!("test {} ... FAILED: {}", name, why);
            }
        }
    }
    let passed = TESTS.len() as u32 - failed;
    hprintln!("target tests: {} passed; {} failed", passed, failed);
    debug::exit(if failed == 0 {
        debug::EXIT_SUCCESS
    } else {
        debug::EXIT_FAILURE
    });
    loop {
        cortex_m::asm::wfi();
    }
}

/// Fails with `why` unless `ok`.
fn check(ok: bool, why: &'static str) -> Outcome {
    if ok {
        Ok(())
    } else {
        Err(why)
    }
}

/// The ADC counts the factory head reads on `plane` (the golden input).
fn counts_on(params: &Params, plane: &Plane<f32>) -> Result<Sample, &'static str> {
    let mut s = Sample::default();
    for i in 0..4 {
        let d = distance(&params.head.sensors[i], plane, i).map_err(|_| "plane not seen")?;
        let tr = &params.transfer[i];
        let sig = perpend_board::acq::signal_for_mm(d, tr);
        s.counts[i] = perpend_board::acq::counts_for_signal(sig, tr, &params.acq);
    }
    s.temp_c = Some(25.0);
    Ok(s)
}

/// The per-sample pipeline in f32 on planes tilted up to 6° and 10°:
/// the normal is the plane's within [`NORMAL_TOL_RAD`].
fn normal_of_tilted_planes_f32() -> Outcome {
    let params = Params::factory();
    for k in 0..8 {
        // a fresh pipeline per plane: the jump detector would drop a
        // reading that steps from one plane to the next
        let mut pipe = Pipeline::new(params, true);
        let t = k as f32 * 0.03;
        let plane =
            Plane::from_abcd(0.02 + t * 0.5, -0.04 + t, 1.0, -42.0 - t).map_err(|_| "plane")?;
        let out = pipe.process(&counts_on(&params, &plane)?);
        check(out.valid(), "pipeline output invalid on a plane in range")?;
        let n = Vector3::new(out.normal[0], out.normal[1], out.normal[2]);
        let angle = n.cross(&plane.n).norm();
        check(
            angle <= NORMAL_TOL_RAD,
            "normal off the plane's by more than 0.05°",
        )?;
    }
    Ok(())
}

/// Issue 33 defect 1 on the board's code: three buffers pending, a
/// cancellation requested and never finished, then a bit-rate switch
/// (CCE resets TXBRP/TXBCF/TXBTO): the three frames come back, the
/// cancellation is forgotten and the next write is accepted.
fn fdcan_switch_with_cancel_outstanding() -> Outcome {
    let mut tx = FdcanTx::new(FakeFdcan::default());
    let mut q = TxQueue::<8>::new();
    for id in [0x300, 0x301, 0x302] {
        check(q.push(Frame::new(id, &[1])), "queue refused a frame")?;
    }
    q.service(&mut tx);
    tx.regs_mut().hold_cancel = true;
    check(q.push(Frame::new(0x100, &[2])), "queue refused a frame")?;
    q.service(&mut tx);
    check(
        tx.is_cancelling(),
        "no cancellation for a higher-priority frame",
    )?;
    tx.regs_mut().rx_fifo = 3;
    tx.regs_mut().ring_room = 8;
    let sw = tx.switch_bitrate(0x0203_0A03);
    check(
        !tx.is_cancelling(),
        "cancellation outlived the bit-rate switch",
    )?;
    check(sw.requeue.len() == 3, "pending frames not read back")?;
    check(
        sw.rx_lost == 0,
        "received frames lost although the ring had room",
    )?;
    check(tx.regs_mut().nbtp == 0x0203_0A03, "NBTP not programmed")?;
    for f in sw.requeue {
        q.requeue(f);
    }
    check(q.service(&mut tx) > 0, "no write accepted after the switch")
}

/// The software queue over the FDCAN fake sends in identifier order and
/// displaces the lowest-priority buffer for a more urgent frame.
fn txq_priority_through_fdcan() -> Outcome {
    let mut tx = FdcanTx::new(FakeFdcan::default());
    let mut q = TxQueue::<8>::new();
    for id in [0x305, 0x304, 0x303, 0x080] {
        q.push(Frame::new(id, &[]));
    }
    for _ in 0..8 {
        q.service(&mut tx);
        tx.regs_mut().tick();
    }
    let sent = &tx.regs_mut().sent;
    check(
        sent.first().map(|f| f.id) == Some(0x080),
        "EMCY-class frame not first",
    )?;
    check(sent.len() == 4, "not every frame was sent")
}

/// The default receive set: NMT and SYNC accepted, SDO to this node
/// accepted, a foreign SDO rejected.
fn rxfilter_default_set() -> Outcome {
    let set = RxSet {
        node_id: 0x20,
        sync: 0x80,
        rpdos: [None; perpend_board::rxfilter::MAX_RPDOS],
        heartbeats: [None; perpend_board::rxfilter::MAX_HEARTBEATS],
        lss: true,
    };
    let f = filters(&set).map_err(|_| "filters rejected the default set")?;
    check(accepts(&f, 0x000).is_some(), "NMT rejected")?;
    check(accepts(&f, 0x080).is_some(), "SYNC rejected")?;
    check(accepts(&f, 0x620).is_some(), "own SDO rejected")?;
    check(accepts(&f, 0x621).is_none(), "foreign SDO accepted")?;
    check(accepts(&f, 0x7E5).is_some(), "LSS master rejected")?;
    check(
        matches!(accepts(&f, 0x620), Some(Fifo::F0 | Fifo::F1)),
        "no FIFO",
    )
}

/// Issue 33 defect 5: one PSR value per tick counts its LEC once; BO
/// starts and ends the bus-off time.
fn busmon_counts_lec_and_bus_off() -> Outcome {
    let mut m = BusMonitor::new();
    // LEC 3 (form error), LEC 7 (no change), LEC 0, BO with LEC 5
    let mut ev = [BusEvent::None; 4];
    for (e, (psr, t)) in ev
        .iter_mut()
        .zip([(3, 10), (7, 20), (0, 30), (0x80 | 5, 40)])
    {
        *e = m.on_psr(psr, t);
    }
    check(
        m.errors() == 2,
        "LEC 3 and 5 counted once each, 7 and 0 not",
    )?;
    check(ev[3] == BusEvent::BusOff, "BO not reported")?;
    check(m.bus_off_for_us(140) == 100, "bus-off time")?;
    check(
        m.on_psr(0, 150) == BusEvent::Recovered,
        "recovery not reported",
    )
}

/// Issue 33 defect 2: a corrected single error and two double errors in
/// one read: the double words are filled, the single error counted.
fn ecc_read_substitutes_double_errors() -> Outcome {
    let mut r = FakeEcc::default();
    r.single_at = Some(8);
    r.double_at = [Some(16), Some(40)];
    let mut buf = [0u8; 48];
    let rep = guarded_read(&mut r, 0, &mut buf).map_err(|_| "too many faults")?;
    let fill = perpend_board::storage::ECC_FILL;
    check(
        rep.substituted == 2 && rep.first == Some(16),
        "double errors",
    )?;
    check(rep.corrected == 1, "single error not counted")?;
    check(
        buf[16..24].iter().all(|&b| b == fill),
        "double word not filled",
    )?;
    check(buf[..8].iter().all(|&b| b != fill), "clean word filled")?;
    check(r.dcache_on, "data cache not restored")
}

/// Parameters with node-id `id` (what the store tests tell apart).
fn params_with(id: u8) -> Params {
    let mut p = Params::factory();
    p.can.node_id = id;
    p
}

/// Store and restore with a power cut at each step of a save over an older
/// record: after the reboot either record loads, never a mix or nothing.
fn storage_cut_at_each_step() -> Outcome {
    let mut st = host_store(FaultFlash::new());
    save(&mut st, &params_with(0x21)).map_err(|_| "first save")?;
    let before = st.flash_mut().steps();
    save(&mut st, &params_with(0x22)).map_err(|_| "second save")?;
    let steps = st.flash_mut().steps() - before;
    check(steps > 0, "a save took no flash step")?;
    for n in 0..steps {
        let mut st = host_store(FaultFlash::new());
        save(&mut st, &params_with(0x21)).map_err(|_| "first save")?;
        st.flash_mut().cut_power_after(n);
        check(
            save(&mut st, &params_with(0x22)).is_err(),
            "cut save succeeded",
        )?;
        let mut flash = st.into_flash();
        flash.power_on();
        let (p, boot) = load(&mut host_store(flash));
        check(boot == Boot::Stored, "nothing valid after a cut")?;
        check(
            matches!(p.can.node_id, 0x21 | 0x22),
            "a mix of records loaded",
        )?;
    }
    Ok(())
}

/// An App over an erased host flash: factory defaults, node 0x20.
fn factory_app() -> App<SeqStore<perpend_board::storage::HostFlash>> {
    App::new(host_store(FaultFlash::new()))
}

/// SDO expedited upload of 0x1000 (device type) from node 0x20.
fn sdo_upload_device_type() -> Outcome {
    let mut app = factory_app();
    app.poll(1_000, &mut |_| {});
    let mut reply = None;
    let req = Frame::new(0x620, &[0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0]);
    app.handle(&req, 2_000, &mut |f: Frame| {
        if f.id == 0x5A0 {
            reply = Some(f);
        }
    });
    let f = reply.ok_or("no SDO response on 0x5A0")?;
    check(f.data[0] & 0xE0 == 0x40, "not an upload response")?;
    check(f.data[1..3] == [0x00, 0x10], "wrong index in the response")
}

/// A sample with every ADC count 0 (open sensors), operational: an EMCY
/// frame on 0x0A0 with a non-zero error code.
fn emcy_on_sensor_fault() -> Outcome {
    let mut app = factory_app();
    let mut emcy = None;
    let mut grab = |f: Frame| {
        if f.id == 0x0A0 {
            emcy = Some(f);
        }
    };
    app.poll(1_000, &mut grab);
    app.handle(&Frame::new(0, &[0x01, 0]), 2_000, &mut grab);
    for k in 0..20u64 {
        app.on_sample(&Sample::default(), 3_000 + k * 1_000);
        app.poll(3_000 + k * 1_000, &mut grab);
    }
    let f = emcy.ok_or("no EMCY frame on 0x0A0")?;
    check(
        u16::from_le_bytes([f.data[0], f.data[1]]) != 0,
        "EMCY code 0",
    )
}

//! The fault matrix (issue 7 item 3) through the whole board application
//! (`perpend_board::app::App`: pipeline, CANopen device, storage) as the
//! robot controller sees it on the bus: status word in TPDO 2, normal in
//! TPDO 3/4, EMCY frames, error register 0x1001 and history 0x1003, and the
//! stored data. Complements `perpend-board`'s `fault_matrix.rs` (pipeline
//! level, status bits) and `app_tests.rs` (one sensor's EMCY, storage):
//! here every sensor × every fault kind, with its EMCY and its clearing,
//! the jump cases, CAN bus-off and recovery, corrupted records.
//!
//! Every sample of every case is checked for "never a wrong normal
//! reported as valid": a valid sample's normal is within 0.25° of the
//! plane's, an invalid one's is exactly zero.
#![allow(missing_docs, clippy::unwrap_used, clippy::panic)]

use nalgebra::Vector3;
use perpend_board::acq::{counts_for_signal, signal_for_mm};
use perpend_board::app::{App, EMCY_CLEAR_SAMPLES};
use perpend_board::pipeline::{Output, Sample};
use perpend_board::status::{
    sensor_bits, sensor_nibble, DEGRADED, NO_PLANE, RESIDUAL_HIGH, SENSOR_OPEN_LOOP,
    SENSOR_OUT_OF_RANGE, SENSOR_OVERCURRENT, SENSOR_STUCK, SENSOR_VALID, UNCALIBRATED,
};
use perpend_board::storage::{host_store, save_with_tail, Boot, HostFlash, SeqStore};
use perpend_can::status::{emcy, error_register};
use perpend_can::{Frame, IMAGE_LEN};
use perpend_core::geometry::Plane;
use perpend_core::model::distance;
use perpend_core::params::Params;
use proptest::prelude::*;

type HostApp = App<SeqStore<HostFlash>>;
const NODE: u16 = 0x20;
/// A valid normal further than this from the truth is a wrong normal.
const WRONG_DEG: f64 = 0.25;

fn plane() -> Plane<f64> {
    Plane::from_abcd(0.035, -0.052, 1.0, -40.0).unwrap()
}

fn true_mm() -> [f32; 4] {
    let head = Params::factory().head.cast::<f64>();
    core::array::from_fn(|i| distance(&head.sensors[i], &plane(), i).unwrap() as f32)
}

fn counts_for_mm(mm: [f32; 4]) -> [u16; 4] {
    let p = Params::factory();
    core::array::from_fn(|i| {
        let t = &p.transfer[i];
        counts_for_signal(signal_for_mm(mm[i], t), t, &p.acq)
    })
}

fn counts_for_ma(ma: f32, i: usize) -> u16 {
    let p = Params::factory();
    counts_for_signal(ma, &p.transfer[i], &p.acq)
}

/// Deterministic noise in [-1, 1).
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((self.0 >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }
}

/// One EMCY frame: code, error register, manufacturer data.
type Emcy = (u16, u8, [u8; 5]);

struct Rig {
    app: HostApp,
    t: u64,
    rng: Lcg,
    /// Frames that reached the bus.
    bus: Vec<Frame>,
    /// While true the controller is bus-off: nothing reaches the bus.
    bus_off: bool,
    worst_valid_deg: f64,
    valid: usize,
    invalid: usize,
}

impl Rig {
    fn new() -> Self {
        let mut r = Self {
            app: App::new(host_store(HostFlash::new())),
            t: 0,
            rng: Lcg(7),
            bus: Vec::new(),
            bus_off: false,
            worst_valid_deg: 0.0,
            valid: 0,
            invalid: 0,
        };
        r.poll();
        r.send(Frame::new(0, &[0x01, NODE as u8]));
        r
    }

    fn out(&mut self, frames: Vec<Frame>) -> Vec<Frame> {
        if !self.bus_off {
            self.bus.extend_from_slice(&frames);
        }
        frames
    }

    fn poll(&mut self) {
        let mut v = Vec::new();
        self.app.poll(self.t, &mut |f| v.push(f));
        self.out(v);
    }

    fn send(&mut self, f: Frame) -> Vec<Frame> {
        self.t += 10;
        let mut v = Vec::new();
        if !self.bus_off {
            self.app.handle(&f, self.t, &mut |g| v.push(g));
        }
        self.out(v)
    }

    /// Distances with ±2 µm of live noise.
    fn live_mm(&mut self) -> [f32; 4] {
        let mut mm = true_mm();
        for v in mm.iter_mut() {
            *v += 0.002 * self.rng.next();
        }
        mm
    }

    /// One sample, a poll and a SYNC; checks the TPDOs against the output
    /// and the "never a wrong normal" rule.
    fn sample(&mut self, counts: [u16; 4]) -> Output {
        self.t += 1000;
        let o = self.app.on_sample(
            &Sample {
                counts,
                ..Sample::default()
            },
            self.t,
        );
        self.poll();
        let pdos = self.send(Frame::new(0x80, &[]));
        if !self.bus_off {
            assert_eq!(pdos.len(), 4, "four TPDOs per SYNC");
            let word = |f: &Frame, k: usize| {
                u32::from_le_bytes(f.data[4 * k..4 * k + 4].try_into().unwrap())
            };
            let st = word(&pdos[1], 0);
            assert_eq!(st, o.status, "TPDO2 carries the status word");
            let n = [
                f32::from_bits(word(&pdos[2], 0)),
                f32::from_bits(word(&pdos[2], 1)),
                f32::from_bits(word(&pdos[3], 0)),
            ];
            assert_eq!(n, o.normal, "TPDO3/4 carry the normal");
        }
        if o.valid() {
            let n = Vector3::new(o.normal[0] as f64, o.normal[1] as f64, o.normal[2] as f64);
            let e = n.angle(&-plane().n).to_degrees();
            assert!(e < WRONG_DEG, "valid but {e}° off: {o:?}");
            self.worst_valid_deg = self.worst_valid_deg.max(e);
            self.valid += 1;
        } else {
            assert_eq!(o.normal, [0.0; 3], "an invalid sample carries no normal");
            assert_eq!((o.theta1_deg, o.theta2_deg), (0.0, 0.0));
            self.invalid += 1;
        }
        o
    }

    fn clean(&mut self) -> Output {
        let mm = self.live_mm();
        self.sample(counts_for_mm(mm))
    }

    fn emcys(&self) -> Vec<Emcy> {
        self.bus
            .iter()
            .filter(|f| f.id == 0x80 + NODE)
            .map(|f| {
                (
                    u16::from_le_bytes([f.data[0], f.data[1]]),
                    f.data[2],
                    [f.data[3], f.data[4], f.data[5], f.data[6], f.data[7]],
                )
            })
            .collect()
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Fault {
    Open,
    Overcurrent,
    SaturatedLow,
    SaturatedHigh,
    Stuck,
    Noisy,
    Spatter,
    HoleEdge,
}

/// Counts of one faulted sample `k` of sensor `i`.
fn faulted(r: &mut Rig, f: Fault, i: usize, stuck_at: u16) -> [u16; 4] {
    let mut mm = r.live_mm();
    match f {
        Fault::Noisy => mm[i] += 0.3 * r.rng.next(),
        Fault::Spatter => mm[i] += 3.0,
        Fault::HoleEdge => mm[i] += 1.5,
        _ => {}
    }
    let mut c = counts_for_mm(mm);
    c[i] = match f {
        Fault::Open => counts_for_ma(0.0, i),
        Fault::Overcurrent => counts_for_ma(24.0, i),
        Fault::SaturatedLow => counts_for_ma(3.7, i),
        Fault::SaturatedHigh => counts_for_ma(20.8, i),
        Fault::Stuck => stuck_at,
        _ => c[i],
    };
    c
}

/// Runs one sensor fault: 30 clean samples, `n` faulted, then clean until
/// the EMCY clears. Returns the faulted outputs and the EMCYs of the run.
fn run_fault(f: Fault, i: usize, n: usize) -> (Rig, Vec<Output>, Vec<Emcy>) {
    let mut r = Rig::new();
    let mut stuck_at = 0;
    for _ in 0..30 {
        let o = r.clean();
        assert_eq!(o.status, UNCALIBRATED | 0x1111);
        // frozen 40 counts (~0.04 mm) off the live value: not a jump, and
        // never equal to a live sample (the detector's anchor is the first
        // stuck sample)
        stuck_at = counts_for_mm(true_mm())[i] + 40;
    }
    let image = image(&r);
    assert!(r.emcys().is_empty());
    let mut outs = Vec::new();
    for _ in 0..n {
        let c = faulted(&mut r, f, i, stuck_at);
        outs.push(r.sample(c));
    }
    // the fault goes away
    for _ in 0..EMCY_CLEAR_SAMPLES + 30 {
        r.clean();
    }
    let e = r.emcys();
    // the persisted objects are unchanged
    assert_eq!(image, self::image(&r));
    (r, outs, e)
}

fn image(r: &Rig) -> Vec<u8> {
    let mut img = [0u8; IMAGE_LEN];
    r.app.device().persistent_image(&mut img);
    img.to_vec()
}

/// Stored data intact: the board's flash was never programmed or erased
/// (every rig starts on an erased flash), and the persisted objects are
/// the boot ones.
fn flash_untouched(r: Rig) {
    assert_eq!(r.app.stores(), 0);
    let f = r.app.into_store().into_flash();
    assert_eq!(f.steps(), 0, "a fault wrote the flash");
    assert!(f.bytes().iter().all(|&b| b == 0xFF));
}

/// Checks the EMCY sequence of a single-sensor fault: exactly the expected
/// code raised once with its data and register bits, then cleared with an
/// error reset, and 0x1003 holding the code.
fn check_raised_and_cleared(r: &Rig, e: &[Emcy], code: u16, reg: u8, data: [u8; 5]) {
    assert!(e.len() >= 2, "{e:04x?}");
    assert_eq!(e[0].0, code, "{e:04x?}");
    assert_eq!(e[0].1, reg | error_register::GENERIC, "{e:04x?}");
    assert_eq!(e[0].2, data, "{e:04x?}");
    assert_eq!(e.last().unwrap().0, 0, "error reset last: {e:04x?}");
    assert_eq!(e.last().unwrap().1, 0);
    assert_eq!(r.app.device().error_register(), 0);
    let hist: Vec<u16> = (1..=r.app.device().read_u32(0x1003, 0).unwrap() as u8)
        .map(|k| r.app.device().read_u32(0x1003, k).unwrap() as u16)
        .collect();
    assert!(hist.contains(&code), "{hist:04x?}");
}

#[test]
fn each_sensor_loop_current_faults_through_the_board() {
    for (f, nib, ma_code) in [
        (Fault::Open, SENSOR_OPEN_LOOP, true),
        (Fault::Overcurrent, SENSOR_OVERCURRENT, true),
        (Fault::SaturatedLow, SENSOR_OUT_OF_RANGE, false),
        (Fault::SaturatedHigh, SENSOR_OUT_OF_RANGE, false),
    ] {
        let mut worst = 0.0f64;
        for i in 0..4 {
            let (r, outs, e) = run_fault(f, i, 50);
            for o in &outs {
                assert_eq!(sensor_nibble(o.status, i), nib, "{f:?} sensor {i}");
                assert_eq!(o.status & (DEGRADED | NO_PLANE), DEGRADED);
                assert_eq!(o.used(), 3);
            }
            let (code, reg) = if ma_code {
                (emcy::sensor_current(i), error_register::CURRENT)
            } else {
                (emcy::sensor_reading(i), error_register::MANUFACTURER)
            };
            check_raised_and_cleared(&r, &e, code, reg, [i as u8 + 1, nib as u8, 0, 0, 0]);
            assert_eq!(
                e.len(),
                2,
                "{f:?} sensor {i}: raised once, cleared once: {e:04x?}"
            );
            worst = worst.max(r.worst_valid_deg);
            flash_untouched(r);
        }
        eprintln!("{f:?}: every sensor: nibble {nib:#x}, degraded, worst valid normal {worst:.4}°");
    }
}

#[test]
fn each_sensor_stuck_through_the_board() {
    let limit = Params::factory().acq.stuck_samples as usize;
    for i in 0..4 {
        let (r, outs, e) = run_fault(Fault::Stuck, i, limit + 20);
        for (k, o) in outs.iter().enumerate() {
            if k < limit {
                assert_eq!(o.status & SENSOR_STUCK, 0, "sensor {i} sample {k}");
            } else {
                assert_eq!(
                    o.status & SENSOR_STUCK,
                    SENSOR_STUCK,
                    "sensor {i} sample {k}"
                );
                assert_eq!(sensor_nibble(o.status, i), 0);
                assert_eq!(o.status & (DEGRADED | NO_PLANE), DEGRADED);
            }
        }
        check_raised_and_cleared(
            &r,
            &e,
            emcy::sensor_reading(i),
            error_register::MANUFACTURER,
            [i as u8 + 1, 0, 1, 0, 0],
        );
        eprintln!(
            "Stuck sensor {i}: flagged after {limit} samples, EMCY {:#06x} data {:?}, worst valid normal {:.4}°",
            e[0].0, e[0].2, r.worst_valid_deg
        );
        flash_untouched(r);
    }
}

#[test]
fn each_sensor_noisy_through_the_board() {
    for i in 0..4 {
        let (r, outs, e) = run_fault(Fault::Noisy, i, 1000);
        let flagged = outs.iter().filter(|o| !o.valid()).count();
        let dropped = outs
            .iter()
            .filter(|o| o.valid() && sensor_nibble(o.status, i) == 0)
            .count();
        for o in outs.iter().filter(|o| !o.valid()) {
            assert_eq!(
                o.status & (RESIDUAL_HIGH | NO_PLANE),
                RESIDUAL_HIGH | NO_PLANE
            );
        }
        // the residual check and the jump detector both act
        assert!(
            flagged > 50 && dropped > 50,
            "{flagged} flagged, {dropped} dropped"
        );
        let codes: Vec<u16> = e.iter().map(|x| x.0).collect();
        assert!(codes.contains(&emcy::NO_PLANE), "{codes:04x?}");
        assert!(codes.contains(&emcy::sensor_reading(i)), "{codes:04x?}");
        assert_eq!(*codes.last().unwrap(), 0);
        assert_eq!(r.app.device().error_register(), 0);
        eprintln!(
            "Noisy sensor {i} (±0.3 mm): {flagged}/1000 flagged no-plane, {dropped} valid with it dropped, \
             worst valid normal {:.4}°, EMCY {:04x?}",
            r.worst_valid_deg,
            codes
        );
        flash_untouched(r);
    }
}

#[test]
fn spatter_and_hole_edge_through_the_board() {
    let hold = Params::factory().acq.jump_hold as usize;
    for i in 0..4 {
        // spatter: +3 mm for 5 samples
        let (r, outs, e) = run_fault(Fault::Spatter, i, 5);
        for o in &outs {
            assert_eq!(sensor_nibble(o.status, i), 0);
            assert_eq!(o.status & (DEGRADED | NO_PLANE | SENSOR_STUCK), DEGRADED);
        }
        check_raised_and_cleared(
            &r,
            &e,
            emcy::sensor_reading(i),
            error_register::MANUFACTURER,
            [i as u8 + 1, 0, 0, 0, 0],
        );
        // hole edge: a permanent +1.5 mm step: held out, then the
        // four-sensor residual flags it; never a valid wrong normal
        let (r2, outs, e2) = run_fault(Fault::HoleEdge, i, 100);
        for (k, o) in outs.iter().enumerate() {
            if k < hold {
                assert_eq!(o.status & (DEGRADED | NO_PLANE), DEGRADED, "sample {k}");
            } else {
                assert_eq!(
                    o.status & (RESIDUAL_HIGH | NO_PLANE),
                    RESIDUAL_HIGH | NO_PLANE,
                    "sample {k}"
                );
                assert_eq!(o.status & 0x1111, 0x1111);
            }
        }
        let codes: Vec<u16> = e2.iter().map(|x| x.0).collect();
        assert!(
            codes.contains(&emcy::sensor_reading(i)) && codes.contains(&emcy::NO_PLANE),
            "{codes:04x?}"
        );
        let np = e2.iter().find(|x| x.0 == emcy::NO_PLANE).unwrap();
        assert_eq!(np.2, [4, 0, 0, 0, 0], "no plane although four sensors read");
        assert_eq!(r2.app.device().error_register(), 0);
        eprintln!(
            "sensor {i}: spatter dropped for {} samples (EMCY {:#06x}); hole edge held {hold} samples then \
             residual-flagged, EMCY {codes:04x?}; worst valid normal {:.4}° / {:.4}°",
            outs.len().min(5),
            e[0].0,
            r.worst_valid_deg,
            r2.worst_valid_deg
        );
        flash_untouched(r);
        flash_untouched(r2);
    }
}

#[test]
fn two_sensors_lost_through_the_board() {
    for a in 0..4 {
        for b in a + 1..4 {
            let mut r = Rig::new();
            for _ in 0..10 {
                r.clean();
            }
            for _ in 0..20 {
                let mut c = counts_for_mm(r.live_mm());
                c[a] = counts_for_ma(1.0, a);
                c[b] = counts_for_ma(22.0, b);
                let o = r.sample(c);
                assert!(!o.valid());
                assert_eq!(
                    o.status & !UNCALIBRATED & 0xFFFF_0000,
                    NO_PLANE,
                    "no degraded/residual bits, only no-plane"
                );
                assert_eq!(sensor_nibble(o.status, a), SENSOR_OPEN_LOOP);
                assert_eq!(sensor_nibble(o.status, b), SENSOR_OVERCURRENT);
            }
            let e = r.emcys();
            let codes: Vec<u16> = e.iter().map(|x| x.0).collect();
            let mut want = vec![
                emcy::sensor_current(a),
                emcy::sensor_current(b),
                emcy::NO_PLANE,
            ];
            want.sort();
            let mut got = codes.clone();
            got.sort();
            assert_eq!(got, want, "{codes:04x?}");
            let np = e.iter().find(|x| x.0 == emcy::NO_PLANE).unwrap();
            assert_eq!(np.2[0], 2, "two sensors valid");
            let reg = r.app.device().error_register();
            assert_eq!(
                reg,
                error_register::GENERIC | error_register::CURRENT | error_register::MANUFACTURER
            );
            assert_eq!(r.invalid, 20);
            flash_untouched(r);
        }
    }
    eprintln!("two sensors lost (6 pairs): no plane, zero normal, EMCY per sensor + 0xFF02 [2,..]");
}

#[test]
fn bus_off_and_recovery() {
    let mut r = Rig::new();
    for _ in 0..20 {
        r.clean();
    }
    let counter_before = r.app.device().sample_counter();
    let image_before = image(&r);
    // 200 ms bus-off; sensor 3 goes open loop meanwhile: its EMCY is
    // produced but cannot reach the bus
    r.bus_off = true;
    let sent_before = r.bus.len();
    for _ in 0..200 {
        let mut c = counts_for_mm(r.live_mm());
        c[2] = counts_for_ma(0.0, 2);
        r.sample(c);
    }
    assert_eq!(r.bus.len(), sent_before);
    // recovery: the driver reports it, the board sends EMCY 0x8140
    r.bus_off = false;
    r.app.bus_off_recovered();
    r.poll();
    let e = r.emcys();
    assert_eq!(e.len(), 2, "{e:04x?}");
    assert_eq!(e[0].0, emcy::BUS_OFF_RECOVERED);
    assert_eq!(
        e[0].1 & (error_register::COMMUNICATION | error_register::GENERIC),
        error_register::COMMUNICATION | error_register::GENERIC
    );
    // its error reset carries the error register that remains: the sensor
    // fault is still active; the controller sees it in the status word,
    // 0x1001 and 0x1003 (its EMCY was lost)
    assert_eq!(e[1].0, 0);
    assert_eq!(
        e[1].1,
        error_register::CURRENT | error_register::GENERIC,
        "{e:04x?}"
    );
    // 0x1029 sub 1 = 0 (the CiA 301 default): the communication error
    // takes the node to pre-operational; the controller starts it again
    assert_eq!(
        r.app.device().nmt_state(),
        perpend_can::NmtState::PreOperational
    );
    r.send(Frame::new(0, &[0x01, NODE as u8]));
    let mut c = counts_for_mm(r.live_mm());
    c[2] = counts_for_ma(0.0, 2);
    let o = r.sample(c);
    assert_eq!(sensor_nibble(o.status, 2), SENSOR_OPEN_LOOP);
    assert_eq!(o.status & DEGRADED, DEGRADED);
    assert!(r.app.device().error_register() & error_register::CURRENT != 0);
    let hist: Vec<u16> = (1..=r.app.device().read_u32(0x1003, 0).unwrap() as u8)
        .map(|k| r.app.device().read_u32(0x1003, k).unwrap() as u16)
        .collect();
    assert!(hist.contains(&emcy::sensor_current(2)) && hist.contains(&emcy::BUS_OFF_RECOVERED));
    // SYNCs are answered again with fresh samples, heartbeat continues
    assert!(r.app.device().sample_counter() > counter_before + 200);
    r.t += 1_000_000;
    r.poll();
    assert!(r
        .bus
        .iter()
        .any(|f| f.id == 0x700 + NODE && f.data[0] == 0x05));
    // the fault clears: error reset after the hold
    for _ in 0..EMCY_CLEAR_SAMPLES + 5 {
        r.clean();
    }
    assert_eq!(r.emcys().last().unwrap().0, 0);
    assert_eq!(r.app.device().error_register(), 0);
    assert_eq!(image(&r), image_before, "stored data untouched");
    // a second bus-off with nothing else active: EMCY then error reset
    r.app.bus_off_recovered();
    r.poll();
    let e = r.emcys();
    let tail: Vec<u16> = e[e.len() - 2..].iter().map(|x| x.0).collect();
    assert_eq!(tail, [emcy::BUS_OFF_RECOVERED, 0]);
    flash_untouched(r);
    eprintln!("bus-off 200 ms: EMCY 0x8140 on recovery, TPDOs resume, sensor fault visible in 0x2005/0x1001/0x1003");
}

#[test]
fn corrupted_device_image_in_a_valid_record_boots_factory_with_emcy() {
    // The record passes its CRC and validation but the CANopen image
    // behind it does not load (here: a TPDO mapping of a calibration
    // object and an out-of-range period): factory defaults, UNCALIBRATED,
    // EMCY 0x6300, no NaN anywhere.
    let mut p = Params::factory();
    p.stamp = 5;
    p.head.sensors[0].zero.x += 0.5;
    let mut img = [0u8; IMAGE_LEN];
    let mut dev = perpend_can::Device::new(NODE as u8, &perpend_board::app::defaults_for(&p));
    dev.load_params(&p).unwrap();
    dev.persistent_image(&mut img);
    for (k, pattern) in [[0xFFu8; 4], [0, 0, 0xC0, 0x7F]].iter().enumerate() {
        let mut bad = img;
        // every word after the header in turn would be too slow; corrupt
        // the last quarter of the image (calibration/config objects)
        for w in (IMAGE_LEN * 3 / 4 / 4..IMAGE_LEN / 4).step_by(3) {
            bad[4 * w..4 * w + 4].copy_from_slice(pattern);
        }
        let mut store = host_store(HostFlash::new());
        save_with_tail(&mut store, &p, &bad).unwrap();
        let mut app = App::new(store);
        assert!(
            matches!(app.boot(), Boot::Rejected(_)),
            "{k}: {:?}",
            app.boot()
        );
        assert!(app.device().emcy_active(emcy::DATA_SET));
        assert_eq!(*app.pipeline().params(), Params::factory());
        let o = app.on_sample(
            &Sample {
                counts: counts_for_mm(true_mm()),
                ..Sample::default()
            },
            1000,
        );
        assert_eq!(o.status & UNCALIBRATED, UNCALIBRATED);
        for (_, index, e) in perpend_can::od::entries() {
            if e.ty == perpend_can::od::DataType::Real32 {
                assert!(app.device().read_f32(index, e.sub).unwrap().is_finite());
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// A stored record that passes its CRC but holds arbitrary values
    /// (forged, or written by a buggy tool): decode never panics; it is
    /// accepted only if every value validates, and then re-encodes to the
    /// same bytes. (The `stored_params` fuzz target rarely gets past the
    /// CRC: 85 edges in 31 M runs.)
    #[test]
    fn record_with_valid_crc_and_arbitrary_payload(
        payload in prop::collection::vec(any::<u8>(), perpend_core::params::PAYLOAD_LEN),
        keep in prop::collection::vec(any::<bool>(), perpend_core::params::PAYLOAD_LEN),
    ) {
        use perpend_core::params::{crc32, RECORD_LEN, HEADER_LEN};
        // mix a valid record with arbitrary bytes so that both accepted and
        // refused records occur
        let mut good = [0u8; RECORD_LEN];
        Params::factory().encode(&mut good).unwrap();
        let mut rec = good;
        for (k, (b, &kp)) in payload.iter().zip(keep.iter()).enumerate() {
            if !kp {
                rec[HEADER_LEN + k] = *b;
            }
        }
        let crc = crc32(&rec[..RECORD_LEN - 4]);
        rec[RECORD_LEN - 4..].copy_from_slice(&crc.to_le_bytes());
        if let Ok(p) = Params::decode(&rec) {
            prop_assert!(p.validate().is_ok());
            let mut again = [0u8; RECORD_LEN];
            p.encode(&mut again).unwrap();
            let q = Params::decode(&again).unwrap();
            prop_assert_eq!(p, q);
        }
    }

    /// A persistence image with the right layout signature and arbitrary
    /// values: `load_image` never panics; on error the device is unchanged;
    /// on success every persisted value is one an SDO write would accept
    /// (the image round-trips and no REAL32 is NaN/inf).
    #[test]
    fn device_image_with_arbitrary_values(
        words in prop::collection::vec(any::<u32>(), (IMAGE_LEN - 8) / 4),
        keep in prop::collection::vec(prop::bool::weighted(0.9), (IMAGE_LEN - 8) / 4),
    ) {
        let mut dev = perpend_can::Device::new(NODE as u8, &perpend_can::Defaults::nominal());
        let mut img = [0u8; IMAGE_LEN];
        dev.persistent_image(&mut img);
        for (k, (w, &kp)) in words.iter().zip(keep.iter()).enumerate() {
            if !kp {
                img[8 + 4 * k..12 + 4 * k].copy_from_slice(&w.to_le_bytes());
            }
        }
        let mut before = [0u8; IMAGE_LEN];
        dev.persistent_image(&mut before);
        match dev.load_image(&img) {
            Ok(()) => {
                let mut out = [0u8; IMAGE_LEN];
                dev.persistent_image(&mut out);
                prop_assert_eq!(&out[..], &img[..]);
                for (_, index, e) in perpend_can::od::entries() {
                    if e.ty == perpend_can::od::DataType::Real32 && e.persist {
                        prop_assert!(dev.read_f32(index, e.sub).unwrap().is_finite());
                    }
                }
            }
            Err(_) => {
                let mut out = [0u8; IMAGE_LEN];
                dev.persistent_image(&mut out);
                prop_assert_eq!(&out[..], &before[..]);
            }
        }
    }
}

#[test]
fn status_bits_are_the_contract() {
    // The bits the matrix relies on are the documented ones (crate docs of
    // perpend-can and perpend-board agree).
    assert_eq!(
        sensor_bits(2, SENSOR_OPEN_LOOP),
        perpend_can::status::sensor_bits(2, perpend_can::status::SENSOR_OPEN_LOOP)
    );
    assert_eq!(
        [
            DEGRADED,
            UNCALIBRATED,
            RESIDUAL_HIGH,
            NO_PLANE,
            SENSOR_STUCK,
            SENSOR_VALID
        ],
        [
            perpend_can::status::DEGRADED,
            perpend_can::status::UNCALIBRATED,
            perpend_can::status::RESIDUAL_HIGH,
            perpend_can::status::NO_PLANE,
            perpend_can::status::SENSOR_STUCK,
            perpend_can::status::SENSOR_VALID
        ]
    );
}

// ---------------------------------------------------------------------------
// Power loss at every flash step of a store, through the board

fn boot(flash: HostFlash) -> HostApp {
    let mut app = App::new(host_store(flash));
    app.poll(0, &mut |_| {});
    app
}

fn write(app: &mut HostApp, index: u16, sub: u8, data: &[u8]) -> [u8; 8] {
    let n = data.len();
    let i = index.to_le_bytes();
    let mut req = [0x23 | (((4 - n) as u8) << 2), i[0], i[1], sub, 0, 0, 0, 0];
    req[4..4 + n].copy_from_slice(data);
    let mut out = Vec::new();
    app.handle(&Frame::new(0x600 + NODE, &req), 100, &mut |f| out.push(f));
    out.iter()
        .find(|f| f.id == 0x580 + NODE)
        .expect("SDO answer")
        .data
}

/// Writes calibration `x` (0x2101 sub 1) and period `period` (0x2300 sub
/// 1) and stores them; returns the store's answer.
fn store(app: &mut HostApp, x: f32, period: u32) -> [u8; 8] {
    assert_eq!(
        write(app, 0x2010, 0, &0x6C61_6375u32.to_le_bytes())[0],
        0x60
    );
    assert_eq!(write(app, 0x2101, 1, &x.to_le_bytes())[0], 0x60);
    assert_eq!(write(app, 0x2300, 1, &period.to_le_bytes())[0], 0x60);
    write(app, 0x1010, 1, &0x6576_6173u32.to_le_bytes())
}

/// The (calibration, period) a board boots with, its boot source, and
/// whether it reports uncalibrated / EMCY 0x6300.
fn booted(flash: HostFlash) -> ((f32, u32), Boot, bool, bool) {
    let mut app = boot(flash);
    let x = app.device().read_f32(0x2101, 1).unwrap();
    let period = app.device().read_u32(0x2300, 1).unwrap();
    let o = app.on_sample(
        &Sample {
            counts: counts_for_mm(true_mm()),
            ..Sample::default()
        },
        1000,
    );
    (
        (x, period),
        app.boot(),
        o.status & UNCALIBRATED != 0,
        app.device().emcy_active(emcy::DATA_SET),
    )
}

#[test]
fn power_loss_at_every_step_of_a_store_through_the_board() {
    let factory = (
        Params::factory().head.sensors[0].zero.x,
        Params::factory().acq.period_us,
    );
    // the first store, one over an old record, and the first one that has
    // to erase a page (found below)
    let mut summary = Vec::new();
    let mut erased = false;
    for earlier in 0usize..12 {
        if earlier > 1 && erased {
            break;
        }
        let mut base = HostFlash::new();
        let mut old = factory;
        for k in 0..earlier {
            let mut app = boot(base);
            let v = (50.5 + k as f32, 1000 + 100 * k as u32);
            assert_eq!(store(&mut app, v.0, v.1)[0], 0x60);
            old = v;
            base = app.into_store().into_flash();
        }
        let new = (61.5f32, 2000u32);
        // an uninterrupted store: how many flash steps it takes
        let mut probe = boot(base.clone());
        assert_eq!(store(&mut probe, new.0, new.1)[0], 0x60);
        let p = probe.into_store().into_flash();
        let (steps, erases) = (p.steps() - base.steps(), p.erases() - base.erases());
        if earlier > 1 && erases == 0 {
            continue;
        }
        erased |= erases > 0;
        let (mut kept_old, mut got_new) = (0, 0);
        for cut in 0..steps {
            let mut f = base.clone();
            f.cut_power_after(cut);
            let mut app = boot(f);
            let r = store(&mut app, new.0, new.1);
            // the store fails: an abort 0x08000020, never a confirmation
            assert_eq!(r[0], 0x80, "cut {cut}");
            assert_eq!(u32::from_le_bytes([r[4], r[5], r[6], r[7]]), 0x0800_0020);
            let mut f = app.into_store().into_flash();
            f.power_on();
            let (vals, src, uncal, data_set) = booted(f);
            // all old or all new, never a mix; never a rejected record
            assert!(vals == old || vals == new, "cut {cut}/{steps}: {vals:?}");
            assert!(!data_set, "cut {cut}: EMCY 0x6300");
            if vals == old {
                kept_old += 1;
            } else {
                got_new += 1;
            }
            if earlier == 0 && vals == old {
                assert_eq!(src, Boot::Missing);
                assert!(uncal, "factory defaults are reported uncalibrated");
            } else {
                assert_eq!(src, Boot::Stored, "cut {cut}");
                assert!(
                    !uncal,
                    "earlier {earlier} cut {cut}/{steps}: {vals:?} {src:?}"
                );
            }
        }
        assert!(kept_old >= steps as usize - 2, "{kept_old} of {steps}");
        summary.push(format!(
            "{earlier} earlier stores: {steps} flash steps ({erases} erases), \
             {kept_old} cuts booted the old values, {got_new} the new, 0 mixed, 0 rejected"
        ));
    }
    assert!(erased, "no store erased a page");
    assert_eq!(summary.len(), 3);
    for s in summary {
        eprintln!("power loss: {s}");
    }
}

//! Instruction-count benchmark of the board's hot paths on a Cortex-M4F,
//! run by `cargo xtask mcu-bench` on QEMU `mps2-an386` with one
//! instruction per translation block and `-d exec,nochain`: xtask counts
//! the executed instructions between calls of [`bench_mark`] (their
//! addresses come from the ELF symbol table) and divides by [`REPS`].
//!
//! Sections (marks 1→2, 3→4, 5→6, 6→7, 9→10, 11→12, 13→14, 15→16,
//! 17→18, 19→20, 21→22, 23→24, 25→26, 27→28, 29→30, 31→32, 33→34; 7→8
//! is the loop baseline that the two square-root sections subtract; 8→9,
//! 10→11, 12→13, 14→15, 16→17, 18→19, 20→21 and each even → odd mark
//! from 22 on are set-up, not reported):
//!
//! 1. the per-sample pipeline exactly as the board runs it: four ADC
//!    results in (a different tilted plane each repetition), status,
//!    normal, θ1/θ2/θ, pitch/yaw, residual
//!    (`perpend_board::pipeline::Pipeline::process`), then the
//!    measurement objects and the default TPDO 1-4 payloads out;
//! 2. one EKF update of the calibration (`perpend_core::calib::ekf::Ekf`,
//!    one reading of one sensor against a known plane), in `f32`;
//! 3. `libm::sqrtf` (software square root, what `nalgebra`/`simba` call);
//! 4. the FPU's `vsqrt.f32`;
//! 5. the pipeline of 1. with the sphere model of object 0x2310
//!    (`R` = 300 mm, issue 14): four ADC results of a sphere in (a
//!    different tilt each repetition), the sphere fitted to the spots and
//!    the normal where the spindle axis meets it, the TPDO payloads out;
//! 6. `perpend_board::app::App::on_sample` with the time set (pipeline,
//!    measurement objects, EMCY state), operational, plane model;
//! 7. `App::handle` of a SYNC: the four default TPDOs built and sent;
//! 8. the sphere pipeline of 5. under 15-17° of tilt, where the fit takes
//!    its second Gauss-Newton step (surface.rs, stopping rule);
//! 9. the pipeline of 1. with an active linearity table on every sensor
//!    (stored-parameter record version 2, [`table_params`]): each reading
//!    is corrected by Newton steps through the spline (ext.rs);
//! 10. the App update of 6. with an active linearity table on every sensor,
//!     written over CAN (0x2101..0x2104 sub 7, 16..23, [`write_tables`]):
//!     knots at ±1.5 mm about `d_ref` = the sensor's mean reading, values
//!     of 21-46 µm, readings carrying the excess the table models;
//! 11. the SYNC of 7. on that App;
//! 12. the App update of 6. with the head's thermal lag on (τ = 600 s in
//!     0x2105, a thermal coefficient on every sensor, [`bench_app_lag`]),
//!     samples 1 ms apart: the expansion from the last commit;
//! 13. the SYNC of 7. on that App;
//! 14. the same App update, samples 1 s apart: every one a commit on the
//!     lag's grid (the step's coefficients are computed once per τ), the
//!     worst sample;
//! 15. to 17. the sections 12 to 14 with the linearity tables of 10.
//!
//! The program exits through semihosting (status 0 on success).

#![no_std]
#![no_main]

use core::hint::black_box;

use cortex_m_rt::entry;
use cortex_m_semihosting::debug;
use perpend_board::app::{measurement_of, App};
use perpend_board::pipeline::{Output, Pipeline, Sample};
use perpend_board::storage::{ParamStore, StoreError};
use perpend_can::Frame;
use perpend_core::calib::ekf::{Ekf, EkfConfig};
use perpend_core::geometry::Plane;
use perpend_core::model::distance;
use perpend_core::params::Params;
use perpend_core::surface::{CurvedSurface, Shape};

/// Repetitions of each section.
const REPS: usize = 16;

/// Marker call: xtask counts the instructions between marks.
#[inline(never)]
#[no_mangle]
pub extern "C" fn bench_mark(id: u32) {
    black_box(id);
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    debug::exit(debug::EXIT_FAILURE);
    cortex_m::asm::udf()
}

// The FPU's square root as a function of the hard-float ABI (argument and
// result in s0).
core::arch::global_asm!(
    ".fpu fpv4-sp-d16",
    ".global perpend_vsqrt",
    ".type perpend_vsqrt,%function",
    ".thumb_func",
    "perpend_vsqrt:",
    "vsqrt.f32 s0, s0",
    "bx lr",
);

extern "C" {
    fn perpend_vsqrt(x: f32) -> f32;
}

/// The FPU's square root (`vsqrt.f32`).
#[inline(never)]
fn vsqrt(x: f32) -> f32 {
    // SAFETY: a leaf function that only reads and writes s0.
    unsafe { perpend_vsqrt(x) }
}

#[inline(never)]
fn soft_sqrt(x: f32) -> f32 {
    libm::sqrtf(x)
}

/// The default TPDO payloads (θ1 θ2 | status counter | nx ny | nz rms).
fn pdo_payloads(o: &Output, counter: u32) -> [[u8; 8]; 4] {
    let m = measurement_of(o);
    let pair = |a: [u8; 4], b: [u8; 4]| {
        let mut p = [0u8; 8];
        p[..4].copy_from_slice(&a);
        p[4..].copy_from_slice(&b);
        p
    };
    [
        pair(m.theta1_deg.to_le_bytes(), m.theta2_deg.to_le_bytes()),
        pair(m.status.to_le_bytes(), counter.to_le_bytes()),
        pair(m.normal[0].to_le_bytes(), m.normal[1].to_le_bytes()),
        pair(m.normal[2].to_le_bytes(), m.rms_mm.to_le_bytes()),
    ]
}

/// Nothing stored: the App boots the factory defaults.
struct NoStore;

impl ParamStore for NoStore {
    fn load(&mut self, _: &mut [u8]) -> Result<Option<usize>, StoreError> {
        Ok(None)
    }
    fn store(&mut self, _: &[u8]) -> Result<(), StoreError> {
        Ok(())
    }
}

/// Sphere model radius of section 5 \[mm\].
const SPHERE_R: f32 = 300.0;

/// REPS samples of a sphere of radius [`SPHERE_R`] under the factory head,
/// tilted a little differently each time (set-up, not measured): about
/// 3° of tilt, or 15-17° with `steep`.
fn sphere_samples(params: &Params, steep: bool) -> [Sample; REPS] {
    let mut samples = [Sample::default(); REPS];
    let base = if steep { 0.3 } else { 0.05 };
    for (k, s) in samples.iter_mut().enumerate() {
        let t = k as f32 * 0.004;
        let n = nalgebra::Vector3::new(0.03 - t, -base + t, -1.0);
        let p = nalgebra::Vector3::new(0.0, 0.0, 45.0 + t * 10.0);
        let Ok(surf) = CurvedSurface::through(p, n, &Shape::Sphere { radius: SPHERE_R }) else {
            fail()
        };
        for i in 0..4 {
            let Ok(d) = surf.distance(&params.head.sensors[i], i) else {
                fail()
            };
            let tr = &params.transfer[i];
            let sig = perpend_board::acq::signal_for_mm(d, tr);
            s.counts[i] = perpend_board::acq::counts_for_signal(sig, tr, &params.acq);
        }
        s.temp_c = Some(25.0);
    }
    samples
}

/// Sections 6 and 7 (marks from 11; `table` false) and 10 and 11 (marks
/// from 19; `table` true): the App's update and SYNC (set-up between
/// marks). With `table`, [`write_tables`] gives every sensor an active
/// linearity table over CAN first, and the readings carry the excess it
/// models (so the corrected spots lie on the plane).
fn bench_app(mark: u32, table: bool) {
    let mut app = App::new(NoStore);
    let mut sent = 0u32;
    let mut now = 1_000u64;
    // Boot-up, the tables (pre-operational), then NMT start (all nodes):
    // the TPDOs are sent on SYNC.
    app.poll(now, &mut |_| sent += 1);
    if table {
        write_tables(&mut app, &mut now);
    }
    app.handle(&Frame::new(0, &[0x01, 0]), now, &mut |_| sent += 1);
    let (mut samples, _) = plane_samples(app.pipeline().params());
    if table {
        add_excess(app.pipeline().params(), &mut samples);
    }
    app.on_sample(&samples[0], now);
    bench_mark(mark);
    let mut ok = 0u32;
    for s in &samples {
        now += 1_000;
        let o = app.on_sample(black_box(s), now);
        ok += u32::from(o.valid());
    }
    bench_mark(mark + 1);
    if ok != REPS as u32 {
        fail();
    }
    let frames = syncs(&mut app, &mut now, mark + 2);
    if frames != 4 * REPS as u32 {
        fail();
    }
    black_box(sent);
}

/// The head's thermal time constant of sections 12-17 \[s\] (0x2105).
const LAG_TAU_S: f32 = 600.0;
/// The thermal coefficient of every sensor in sections 12-17 \[mm/°C\]
/// (0x2101..0x2104 sub 13).
const LAG_THERMAL: f32 = 0.002;

/// Sections 12-14 (marks from 23; `table` false) and 15-17 (marks from
/// 29; `table` true): the App's update and SYNC of 6/7 (10/11 with
/// `table`) with the thermal lag on: τ = [`LAG_TAU_S`] and a thermal
/// coefficient on every sensor, written over CAN, a die temperature
/// warming by 1 mK per sample. 12/15: 1 ms apart, the second-order
/// expansion from the last commit (what 999 of 1000 samples at 1 kHz
/// do); 13/16: the SYNC; 14/17: 1 s apart, every sample a commit on the
/// lag's grid (multiply-adds with the coefficients cached per τ, the
/// worst sample, once a second; a sample 2P or more after the last
/// commit would take `lag::step` with `expm1f`).
fn bench_app_lag(mark: u32, table: bool) {
    let mut app = App::new(NoStore);
    let mut sent = 0u32;
    let mut now = 1_000u64;
    app.poll(now, &mut |_| sent += 1);
    if table {
        write_tables(&mut app, &mut now);
    }
    write_lag(&mut app, &mut now);
    app.handle(&Frame::new(0, &[0x01, 0]), now, &mut |_| sent += 1);
    let (mut samples, _) = plane_samples(app.pipeline().params());
    if table {
        add_excess(app.pipeline().params(), &mut samples);
    }
    for (k, s) in samples.iter_mut().enumerate() {
        s.temp_c = Some(25.0 + 0.001 * k as f32);
    }
    // at rest at the first temperature, then one committed step: the
    // 1 ms samples that follow are all within the commit interval
    app.on_sample(&samples[0], now);
    now += 1_000_000;
    app.on_sample(&samples[0], now);
    bench_mark(mark);
    let ok = lag_samples(&mut app, &samples, &mut now, 1_000);
    bench_mark(mark + 1);
    let frames = syncs(&mut app, &mut now, mark + 2);
    // back in reverse order: no jump from the last plane to the first
    samples.reverse();
    bench_mark(mark + 4);
    let ok2 = lag_samples(&mut app, &samples, &mut now, 1_000_000);
    bench_mark(mark + 5);
    if ok != REPS as u32 || ok2 != REPS as u32 || frames != 4 * REPS as u32 {
        fail();
    }
    black_box(sent);
}

/// Unlocks and writes τ = [`LAG_TAU_S`] (0x2105) and the thermal
/// coefficient [`LAG_THERMAL`] of every sensor (set-up); fails unless the
/// pipeline holds them.
fn write_lag(app: &mut App<NoStore>, now: &mut u64) {
    sdo_write(app, now, 0x2010, 0, 0x6C61_6375u32.to_le_bytes());
    sdo_write(app, now, 0x2105, 0, LAG_TAU_S.to_le_bytes());
    for i in 0..4u16 {
        sdo_write(app, now, 0x2101 + i, 13, LAG_THERMAL.to_le_bytes());
    }
    let p = app.pipeline().params();
    let coeffs = p.head.sensors.iter().all(|s| s.ext.thermal == LAG_THERMAL);
    if p.thermal_tau_s != LAG_TAU_S || !coeffs || !app.pipeline().config_ok() {
        fail()
    }
}

/// `samples` through the App, `step_us` apart (measured); returns how
/// many outputs were valid.
fn lag_samples(app: &mut App<NoStore>, samples: &[Sample], now: &mut u64, step_us: u64) -> u32 {
    let mut ok = 0u32;
    for s in samples {
        *now += step_us;
        ok += u32::from(app.on_sample(black_box(s), *now).valid());
    }
    ok
}

/// [`REPS`] SYNCs between marks `mark` and `mark + 1`; returns the frames
/// sent. Not inlined: every SYNC section measures the same code of
/// `App::handle` (inlined into each caller it came out 22 instructions
/// apart between sections 7 and 13).
#[inline(never)]
fn syncs(app: &mut App<NoStore>, now: &mut u64, mark: u32) -> u32 {
    let sync = Frame::new(0x80, &[]);
    let mut frames = 0u32;
    bench_mark(mark);
    for _ in 0..REPS {
        *now += 1_000;
        app.handle(black_box(&sync), *now, &mut |f| {
            black_box(f);
            frames += 1;
        });
    }
    bench_mark(mark + 1);
    frames
}

/// Expedited SDO download of 4 bytes to the App's node (set-up); fails the
/// bench on an abort.
fn sdo_write(app: &mut App<NoStore>, now: &mut u64, index: u16, sub: u8, v: [u8; 4]) {
    let node = u16::from(app.pipeline().params().can.node_id);
    let mut p = [0x23, 0, 0, sub, v[0], v[1], v[2], v[3]];
    p[1..3].copy_from_slice(&index.to_le_bytes());
    *now += 100;
    let mut acked = false;
    app.handle(&Frame::new(0x600 + node, &p), *now, &mut |f| {
        acked |= f.id == 0x580 + node && f.data[0] == 0x60;
    });
    if !acked {
        fail()
    }
}

/// Half-width of the table knots about `d_ref` in sections 10 and 11 \[mm\].
const TABLE_HALF_SPAN: f32 = 1.5;

/// Gives every sensor an active linearity table over CAN (0x2101..0x2104,
/// as a calibration tool writes one; set-up): `d_ref` (sub 7) the mean
/// reading of [`plane_samples`], knots at ±[`TABLE_HALF_SPAN`] and halfway
/// about it (sub 16..20), values of 21-46 µm at the interior knots (sub
/// 21..23). Fails unless every reading lies within the knots.
fn write_tables(app: &mut App<NoStore>, now: &mut u64) {
    let params = *app.pipeline().params();
    let (samples, planes) = plane_samples(&params);
    black_box(samples);
    sdo_write(app, now, 0x2010, 0, 0x6C61_6375u32.to_le_bytes());
    let h = TABLE_HALF_SPAN;
    for i in 0..4 {
        let s = &params.head.sensors[i];
        let (mut lo, mut hi, mut sum) = (f32::MAX, f32::MIN, 0.0f32);
        for p in &planes {
            let Ok(Ok(d)) = p.as_ref().map(|p| distance(s, p, i)) else {
                fail()
            };
            (lo, hi, sum) = (lo.min(d), hi.max(d), sum + d);
        }
        let d_ref = sum / REPS as f32;
        if lo < d_ref - h || hi > d_ref + h {
            fail()
        }
        let k = i as f32;
        let knots = [-h, -0.5 * h, 0.0, 0.5 * h, h];
        let values = [0.03 + 0.004 * k, -0.04 + 0.002 * k, 0.025 - 0.001 * k];
        let index = 0x2101 + i as u16;
        sdo_write(app, now, index, 7, d_ref.to_le_bytes());
        for (j, v) in knots.iter().chain(values.iter()).enumerate() {
            sdo_write(app, now, index, 16 + j as u8, v.to_le_bytes());
        }
        if !app.pipeline().params().head.sensors[i]
            .ext
            .table
            .is_active()
        {
            fail()
        }
    }
    if !app.pipeline().config_ok() {
        fail()
    }
}

/// Adds to each reading of `samples` the excess the sensors' extensions
/// model (set-up): the counts then read `f + δ(f)` for the true distance
/// `f` of the plane.
fn add_excess(params: &Params, samples: &mut [Sample; REPS]) {
    let (_, planes) = plane_samples(params);
    let ctx = perpend_core::ext::Context::default();
    for (s, p) in samples.iter_mut().zip(planes.iter()) {
        let Ok(p) = p else { fail() };
        for i in 0..4 {
            let sensor = &params.head.sensors[i];
            let Ok(f) = distance(sensor, p, i) else {
                fail()
            };
            let d = f + sensor.ext.excess(f, None, 1.0, &ctx);
            let tr = &params.transfer[i];
            let sig = perpend_board::acq::signal_for_mm(d, tr);
            s.counts[i] = perpend_board::acq::counts_for_signal(sig, tr, &params.acq);
        }
    }
}

fn fail() -> ! {
    debug::exit(debug::EXIT_FAILURE);
    cortex_m::asm::udf()
}

/// REPS tilted planes and their ADC results under `params` (set-up, not
/// measured).
fn plane_samples(params: &Params) -> ([Sample; REPS], [perpend_core::Result<Plane<f32>>; REPS]) {
    let mut samples = [Sample::default(); REPS];
    let mut planes = [Plane::from_abcd(0.0f32, 0.0, 1.0, -40.0); REPS];
    for (k, (s, pk)) in samples.iter_mut().zip(planes.iter_mut()).enumerate() {
        let t = k as f32 * 0.004;
        let Ok(plane) = Plane::from_abcd(0.03 - t, -0.05 + t, 1.0, -40.0 - t * 10.0) else {
            fail()
        };
        *pk = Ok(plane);
        for i in 0..4 {
            let Ok(d) = distance(&params.head.sensors[i], &plane, i) else {
                fail()
            };
            let tr = &params.transfer[i];
            let sig = perpend_board::acq::signal_for_mm(d, tr);
            s.counts[i] = perpend_board::acq::counts_for_signal(sig, tr, &params.acq);
        }
        s.temp_c = Some(25.0);
    }
    (samples, planes)
}

/// The factory parameters with an active linearity table on every sensor:
/// knots 10 mm apart about the reference distance (50 mm), values of
/// 25-46 µm at the interior knots (a sensor's linearity error within its
/// datasheet's ±0.05 % of a 100 mm range).
fn table_params() -> Params {
    let mut p = Params::factory();
    for (i, s) in p.head.sensors.iter_mut().enumerate() {
        let k = i as f32;
        s.ext.table = perpend_core::ext::LinTable {
            knots: [-20.0, -10.0, 0.0, 10.0, 20.0],
            coeffs: [0.03 + 0.002 * k, -0.04, 0.025],
        };
    }
    if p.validate().is_err() {
        fail()
    }
    p
}

/// Runs `samples` through `pl`, the TPDO payloads of each output built
/// (measured); returns how many outputs were valid.
fn run_samples(pl: &mut Pipeline, samples: &[Sample]) -> u32 {
    let mut ok = 0u32;
    for (k, s) in samples.iter().enumerate() {
        let o = pl.process(black_box(s));
        ok += u32::from(o.valid());
        black_box(pdo_payloads(&o, k as u32));
    }
    ok
}

#[entry]
fn main() -> ! {
    let params = Params::factory();
    let mut pl = Pipeline::new(params, true);
    let (samples, planes) = plane_samples(&params);
    // Warm-up sample (first-sample branches of the detectors).
    black_box(pl.process(&samples[0]));

    bench_mark(1);
    let ok = run_samples(&mut pl, &samples);
    bench_mark(2);
    if ok != REPS as u32 {
        fail();
    }

    let Ok(mut ekf) = Ekf::new(&params.head.sensors[0], 0, EkfConfig::chen_simulation()) else {
        fail()
    };
    let mut readings = [0.0f32; REPS];
    for (r, p) in readings.iter_mut().zip(planes.iter()) {
        let Ok(p) = p else { fail() };
        let Ok(d) = distance(&params.head.sensors[0], p, 0) else {
            fail()
        };
        *r = d + 0.01;
    }
    bench_mark(3);
    for (p, d) in planes.iter().zip(readings.iter()) {
        let Ok(p) = p else { fail() };
        black_box(ekf.update(black_box(p), black_box(*d)).is_ok());
    }
    bench_mark(4);

    let mut acc = 0.0f32;
    bench_mark(5);
    for k in 0..REPS {
        acc += soft_sqrt(black_box(2.0 + k as f32));
    }
    bench_mark(6);
    for k in 0..REPS {
        acc += vsqrt(black_box(2.0 + k as f32));
    }
    bench_mark(7);
    // baseline: the same loop without a square root
    for k in 0..REPS {
        acc += black_box(2.0 + k as f32);
    }
    bench_mark(8);
    black_box(acc);

    let sphere = sphere_samples(&params, false);
    let steep = sphere_samples(&params, true);
    let mut pl_steep = Pipeline::new(params, true);
    pl_steep.set_shape(Shape::Sphere { radius: SPHERE_R });
    let mut pl = Pipeline::new(params, true);
    pl.set_shape(Shape::Sphere { radius: SPHERE_R });
    black_box(pl.process(&sphere[0]));
    bench_mark(9);
    let ok = run_samples(&mut pl, &sphere);
    bench_mark(10);
    if ok != REPS as u32 {
        fail();
    }

    bench_app(11, false);

    black_box(pl_steep.process(&steep[0]));
    bench_mark(15);
    let ok = run_samples(&mut pl_steep, &steep);
    bench_mark(16);
    if ok != REPS as u32 {
        fail();
    }

    let tabled = table_params();
    let (samples, _) = plane_samples(&tabled);
    let mut pl = Pipeline::new(tabled, true);
    black_box(pl.process(&samples[0]));
    bench_mark(17);
    let ok = run_samples(&mut pl, &samples);
    bench_mark(18);
    if ok != REPS as u32 {
        fail();
    }

    bench_app(19, true);
    bench_app_lag(23, false);
    bench_app_lag(29, true);
    debug::exit(debug::EXIT_SUCCESS);
    loop {
        cortex_m::asm::wfi();
    }
}

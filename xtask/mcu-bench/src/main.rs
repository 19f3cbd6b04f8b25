//! Instruction-count benchmark of the board's hot paths on a Cortex-M4F,
//! run by `cargo xtask mcu-bench` on QEMU `mps2-an386` with one
//! instruction per translation block and `-d exec,nochain`: xtask counts
//! the executed instructions between calls of [`bench_mark`] (their
//! addresses come from the ELF symbol table) and divides by [`REPS`].
//!
//! Sections (marks 1→2, 3→4, 5→6, 6→7; 7→8 is the loop baseline that the
//! two square-root sections subtract):
//!
//! 1. the per-sample pipeline exactly as the board runs it: four ADC
//!    results in (a different tilted plane each repetition), status,
//!    normal, θ1/θ2/θ, pitch/yaw, residual
//!    (`perpend_board::pipeline::Pipeline::process`), then the
//!    measurement objects and the default TPDO 1-4 payloads out;
//! 2. one EKF update of the calibration (`perpend_core::calib::ekf::Ekf`,
//!    one reading of one sensor against a known plane), in `f32`;
//! 3. `libm::sqrtf` (software square root, what `nalgebra`/`simba` call);
//! 4. the FPU's `vsqrt.f32`.
//!
//! The program exits through semihosting (status 0 on success).

#![no_std]
#![no_main]

use core::hint::black_box;

use cortex_m_rt::entry;
use cortex_m_semihosting::debug;
use perpend_board::app::measurement_of;
use perpend_board::pipeline::{Output, Pipeline, Sample};
use perpend_core::calib::ekf::{Ekf, EkfConfig};
use perpend_core::geometry::Plane;
use perpend_core::model::distance;
use perpend_core::params::Params;

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

fn fail() -> ! {
    debug::exit(debug::EXIT_FAILURE);
    cortex_m::asm::udf()
}

#[entry]
fn main() -> ! {
    let params = Params::factory();
    let mut pl = Pipeline::new(params, true);
    // REPS tilted planes and their ADC results (setup, not measured).
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
    // Warm-up sample (first-sample branches of the detectors).
    black_box(pl.process(&samples[0]));

    bench_mark(1);
    let mut ok = 0u32;
    for (k, s) in samples.iter().enumerate() {
        let o = pl.process(black_box(s));
        ok += u32::from(o.valid());
        black_box(pdo_payloads(&o, k as u32));
    }
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
    debug::exit(debug::EXIT_SUCCESS);
    loop {
        cortex_m::asm::wfi();
    }
}

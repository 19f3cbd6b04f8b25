//! # perpend-core
//!
//! The measurement core of the perpend surface-normal sensor board: what four
//! (or more) laser displacement sensors on a drilling end-effector's pressure
//! foot tell about the micro-plane under the tool, and how the head that
//! carries them is calibrated.
//!
//! The crate is `no_std`, uses no allocator, sizes every buffer in its types
//! and is generic over the float type ([`Real`]): the board runs it in `f32`,
//! the host tool and the tests in `f64`.
//!
//! Papers the code follows (equation numbers are cited in each item's docs):
//!
//! * **Chen 2018** — D. Chen et al., *A Normal Sensor Calibration Method Based
//!   on an Extended Kalman Filter for Robotic Drilling*, Sensors 18 (2018).
//!   Beam/plane measurement model (eq. 1-9), EKF identification (eq. 10-16),
//!   spot points (eq. 17), micro-plane normal (eq. 18-19), attitude (eq. 20-22).
//! * **Tian 2013** — W. Tian et al., *Auto-normalization algorithm for robotic
//!   precision drilling system in aircraft component assembly*, Chinese
//!   Journal of Aeronautics 26 (2013). Deviation angles θ1/θ2/θ/t1 (eq. 1-5),
//!   direct formula from h1..h4 for a cone-mounted head (eq. 6-12), inverse
//!   target attitude (eq. 13-19).
//!
//! ## Coordinate system
//!
//! Everything is expressed in the tool coordinate system (TCS) of the
//! exchange format: origin at the tool centre point, **+z along the spindle
//! feed**. Tian puts the spindle on X'; the mapping of his axes is documented
//! once, in [`angles`].
//!
//! ## Modules
//!
//! * [`geometry`] — planes, unit vectors, tangent bases.
//! * [`head`] — the sensor head: zero points, beam directions, 5-DOF updates.
//! * [`model`] — the beam/plane measurement model and its Jacobians.
//! * [`ext`] — model extensions: corrections of the reading beyond the paper.
//! * [`lag`] — first-order lag of the head temperature (sensor bodies).
//! * [`normal`] — spots, micro-plane normal (two methods), three-sensor mode.
//! * [`surface`] — the normal at the spindle-axis point of a sphere or
//!   cylinder of known radius (the micro-plane's bias on curved skins).
//! * [`angles`] — deviation and attitude angles, Euler solutions.
//! * [`calib`] — calibration: the paper's EKF and batch least squares.
//! * [`params`] — the stored-parameter record (versioned, checksummed).
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![deny(missing_docs)]

pub mod angles;
pub mod calib;
pub mod error;
pub mod ext;
pub mod geometry;
pub mod head;
pub mod lag;
pub mod model;
pub mod normal;
pub mod params;
pub mod surface;

pub use error::Error;

/// Result type of this crate.
pub type Result<T> = core::result::Result<T, Error>;

/// The float type the math is generic over: `f32` on the board, `f64` on the
/// host. Any [`nalgebra::RealField`] that is `Copy` qualifies.
pub trait Real: nalgebra::RealField + Copy {
    /// Converts an `f64` literal (a constant of the algorithm) to `Self`.
    fn lit(x: f64) -> Self;
    /// Converts `self` to `f64` (for reporting).
    fn to_f64(self) -> f64;
    /// Whether the value is neither NaN nor infinite.
    fn is_finite_real(self) -> bool;
    /// Square root, correctly rounded like [`nalgebra::ComplexField::sqrt`],
    /// but on the Cortex-M4F (`f32`, Arm EABI hard-float) computed by the
    /// FPU's `vsqrt.f32` (7 instructions per call measured on QEMU against
    /// 81 for `libm::sqrtf`, which nalgebra uses on `no_std`). The hot path
    /// of the per-sample pipeline calls this instead of `.sqrt()`/`.norm()`.
    #[inline]
    fn fast_sqrt(self) -> Self {
        self.sqrt()
    }
}

// The FPU square root as a leaf function: `core` has no stable `f32::sqrt`
// on `no_std`, and the `sreg` inline-asm operand class needs the `vfp2`
// feature, which this single-precision target does not name.
#[cfg(all(target_arch = "arm", target_os = "none", target_abi = "eabihf"))]
core::arch::global_asm!(
    ".fpu fpv4-sp-d16",
    ".section .text.perpend_core_vsqrt,\"ax\",%progbits",
    ".global perpend_core_vsqrt",
    ".type perpend_core_vsqrt,%function",
    ".thumb_func",
    "perpend_core_vsqrt:",
    "vsqrt.f32 s0, s0",
    "bx lr",
);

#[cfg(all(target_arch = "arm", target_os = "none", target_abi = "eabihf"))]
extern "C" {
    fn perpend_core_vsqrt(x: f32) -> f32;
}

impl Real for f32 {
    #[inline]
    fn lit(x: f64) -> Self {
        x as f32
    }
    #[inline]
    fn to_f64(self) -> f64 {
        self as f64
    }
    #[inline]
    fn is_finite_real(self) -> bool {
        self.is_finite()
    }
    #[cfg(all(target_arch = "arm", target_os = "none", target_abi = "eabihf"))]
    #[inline]
    fn fast_sqrt(self) -> Self {
        // SAFETY: a leaf function that reads its argument from s0 and
        // returns the square root in s0 (AAPCS-VFP), touching nothing else.
        unsafe { perpend_core_vsqrt(self) }
    }
}

impl Real for f64 {
    #[inline]
    fn lit(x: f64) -> Self {
        x
    }
    #[inline]
    fn to_f64(self) -> f64 {
        self
    }
    #[inline]
    fn is_finite_real(self) -> bool {
        self.is_finite()
    }
}

/// Checks that a scalar input is finite, naming it in the error.
#[inline]
pub(crate) fn finite<T: Real>(x: T, what: &'static str) -> Result<T> {
    if x.is_finite_real() {
        Ok(x)
    } else {
        Err(Error::NonFinite(what))
    }
}

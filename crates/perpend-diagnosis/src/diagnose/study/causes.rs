//! The candidate causes and nuisance parameters of `perpend study paper`,
//! each with the range of its magnitude and where that range comes from.
//!
//! Sources: Chen 2018 (§5, §6, Tables 5-8); Leica's tracker specification
//! (ISO 10360-10 MPE; "typical results are half of the MPE"); the Siemens
//! S7-300 module manual (SM 331 analog inputs: basic error limit
//! ±0.2-0.6 %, temperature error ±0.004-0.005 %/K, linearity ±0.03-0.05 %,
//! repeat accuracy ±0.05-0.1 %, crosstalk > 50 dB, all of the input range);
//! Slamani, Nubiola, Bonev, Industrial Robot 39(1) 2012 (ISO 9283 tests of
//! an industrial robot: orientation repeatability ≤ 87 µrad, rotation
//! accuracy ≤ 2.8 mrad). Chen names neither the laser sensor nor the
//! analog module; the 315T-2DP is an S7-300 CPU, so the SM 331 family is
//! the likely front end. Ranges that rest on an assumption say so.
//!
//! Limits: the sensor's measuring range (50 mm) converts the front end's
//! %-of-range figures to mm; it is assumed (the readings are ~40 mm).

pub use super::model::name;
use super::model::Cause;
use perpend_calib::candidates::Effect;

/// Assumed measuring range of the laser sensors [mm] (converts the
/// front end's %-of-range figures).
pub const SENSOR_RANGE_MM: f64 = 50.0;
/// Distance of the datum plane from the tracker [m]: Chen Table 5, D = −1690 mm.
pub const TRACKER_DISTANCE_M: f64 = 1.69;

/// The candidate causes, in report order.
pub const CANDIDATES: [Cause; 10] = [
    Cause::Tcs,
    Cause::Form,
    Cause::Robot,
    Cause::Sensor(Effect::Gain),
    Cause::Sensor(Effect::Nonlinearity),
    Cause::Sensor(Effect::Incidence),
    Cause::Sensor(Effect::Crosstalk),
    Cause::Sensor(Effect::Thermal),
    Cause::Sensor(Effect::Drift),
    Cause::Ripple,
];

/// Multiples of a cause's upper bound the study tries (those ≤ 1 are
/// inside the sourced range).
pub const SCAN: [f64; 5] = [0.25, 0.5, 1.0, 2.0, 4.0];

/// Reading noise ζ [µm] of the ζ × ξ grid.
pub const ZETA_UM: [f64; 5] = [3.0, 6.0, 10.0, 18.0, 25.0];
/// Tracker point noise ξ [µm] of the ζ × ξ grid.
pub const XI_UM: [f64; 4] = [6.0, 13.0, 25.0, 50.0];
/// Full range of the test attitudes [deg] of the tilt scan.
pub const TILT_DEG: [f64; 6] = [0.5, 1.0, 2.0, 5.0, 10.0, 20.0];
/// Offset of the test standoff from the calibration standoff [mm] of the
/// standoff × robot grid.
pub const STANDOFF_MM: [f64; 8] = [-10.0, -5.0, 0.0, 5.0, 10.0, 15.0, 20.0, 25.0];
/// Robot reorientation error [deg, 1σ per axis] of the standoff × robot
/// grid.
pub const ROBOT_DEG: [f64; 6] = [0.0, 0.005, 0.02, 0.05, 0.1, 0.16];

/// Where the nuisance ranges come from (name, range, source).
pub const NUISANCES: [(&str, &str, &str); 5] = [
    (
        "reading noise ζ",
        "3-25 µm (1σ)",
        "Chen §6 filter R = 9·10⁻⁶ mm² ↔ 3 µm if R is the reading variance, as in §5 where R = 8·10⁻⁵ pairs with ζ = 10 µm; \
         SM 331 repeat accuracy ±0.05-0.1 % of a 50 mm range = 25-50 µm as a bound",
    ),
    (
        "tracker noise ξ",
        "6-25 µm (1σ per coordinate; 50 µm as a stress value)",
        "Chen §6: ADM 7.5 µm + 3 µm/m = 12.6 µm at 1.69 m (Table 5: D = −1690 mm); Leica's ISO 10360-10 MPE for its absolute \
         trackers (AT500 manual: transverse 15 µm + 6 µm/m = 25 µm at 1.69 m; typical results half the MPE)",
    ),
    (
        "test attitudes",
        "0.5-20° full range about both axes",
        "Chen §4.2: the robot turns the spindle until the head reads it perpendicular, so the tests end within the head's \
         own error (~0.5°) of the perpendicular; 20° = the calibration spread assumed here",
    ),
    (
        "test standoff",
        "−10 to +25 mm from the calibration standoff",
        "not stated by Chen (§6: 'the measurement distances are within the sensor range'); ±5 mm around it in each case",
    ),
    (
        "robot reorientation error",
        "0-0.16° (1σ per axis)",
        "Slamani et al. 2012: orientation repeatability ≤ 87 µrad (0.005°), rotation accuracy ≤ 2.8 mrad (0.16°) of a \
         non-calibrated ABB IRB 1600 (no such figures are published for Chen's KUKA KR210); Chen's closed loop (§4.2) \
         leaves a residual between the two",
    ),
];

/// What a cause's magnitude means.
pub fn unit(c: Cause) -> &'static str {
    match c {
        Cause::Sensor(Effect::Gain) => "relative gain error",
        Cause::Sensor(Effect::Nonlinearity) => "peak linearity error over the 50 mm range [mm]",
        Cause::Sensor(Effect::Incidence) => "bias per unit of 1/cos γ − 1 [mm]",
        Cause::Sensor(Effect::Crosstalk) => "carry-over fraction",
        Cause::Sensor(Effect::Thermal) => "drift [mm/°C]",
        Cause::Sensor(Effect::Drift) => "drift [mm/s]",
        Cause::Sensor(_) => "-",
        Cause::Ripple => "amplitude [mm], period 1.5-3 mm",
        Cause::Tcs => "1σ per axis [deg]",
        Cause::Form => "RMS height [mm]",
        Cause::Robot => "1σ per axis [deg]",
    }
}

/// Upper end of a cause's range and its source (module docs).
pub fn upper(c: Cause) -> (f64, &'static str) {
    match c {
        Cause::Tcs => (
            0.02,
            "tracker point error 6-25 µm (row ξ) over a 100-300 mm target baseline on the effector (assumed): \
             √2·ξ/baseline = 0.002-0.02°",
        ),
        Cause::Form => (
            0.015,
            "assumption: Chen says only 'a datum plane on a fixture with high stiffness'; 15 µm RMS ≈ 50 µm \
             peak-to-valley, a machined plate (a lapped surface plate is a few µm)",
        ),
        Cause::Robot => (0.16, "Slamani et al. 2012 rotation accuracy 2.8 mrad (row robot above)"),
        Cause::Sensor(Effect::Gain) => (0.006, "SM 331 basic error limit ±0.2-0.6 % of range, taken as a gain error"),
        Cause::Sensor(Effect::Nonlinearity) => (
            0.025,
            "SM 331 linearity ±0.03-0.05 % of range = 15-25 µm on 50 mm (the sensor's own is unknown)",
        ),
        Cause::Sensor(Effect::Incidence) => (0.1, "assumption (no sensor datasheet): 0.1 mm at 1/cos γ − 1 = 1"),
        Cause::Sensor(Effect::Crosstalk) => (0.003, "SM 331 (2-channel) crosstalk > 50 dB = 0.3 %"),
        Cause::Sensor(Effect::Thermal) => (
            0.0025,
            "SM 331 temperature error ±0.005 %/K of 50 mm = 2.5 µm/°C (the sensor's own is unknown)",
        ),
        Cause::Sensor(Effect::Drift) => (1.7e-5, "assumption: 1 µm/min warm-up drift"),
        Cause::Sensor(_) => (0.0, "-"),
        Cause::Ripple => (0.005, "assumption: 5 µm periodic (fringe/pixel) error"),
    }
}

//! The per-sample pipeline: four ADC results in; status word, normal,
//! Tian's θ1/θ2/θ (eq. 1-5), Chen's pitch/yaw (eq. 22) and the plane
//! residual out, in `f32` as on the board.
//!
//! Steps for every sample:
//!
//! 1. each channel: counts → signal → mm and its NE43 class
//!    ([`crate::acq::convert`]); a channel that is not valid, is stuck, or
//!    jumped is dropped (its reading becomes `None`);
//! 2. the valid readings → spots (Chen eq. 17, with the sensors' extension
//!    corrections, head temperature and run time as context) → micro-plane
//!    (least squares or Chen eq. 18-19) → deviation and attitude, by
//!    `perpend_core::normal::measure_with`, unchanged from the host, with
//!    the sensors' extensions prepared once where the parameters are set
//!    ([`Pipeline::new`]; `perpend_core::ext`, "Prepared form"); with a
//!    curved surface model (object 0x2310, [`Pipeline::set_shape`]) the
//!    sphere or cylinder is fitted to the spots and the normal is the one
//!    where the spindle axis meets it (`perpend_core::surface::measure_with`,
//!    issue 14; the residual is then the RMS distance of the spots from
//!    the fitted surface);
//! 3. plausibility: three sensors → [`DEGRADED`]; four sensors with a plane
//!    RMS residual above `max_rms_mm` → [`RESIDUAL_HIGH`]; any error of the
//!    core or a non-finite result → [`NO_PLANE`].
//!
//! ## Invalid-output policy (NaN-free)
//!
//! The output is a measurement only when [`NO_PLANE`] is clear. While it is
//! set, the normal, the angles and the residual are **zero** (a zero normal
//! is not a unit vector, so it cannot be mistaken for one) and never NaN or
//! infinite; the readings always hold the converted distance of every
//! channel (finite for every ADC result), whatever its class. A wrong normal
//! is therefore never reported as valid as far as these checks can see:
//! with only three sensors the plane is exact, and a wrong reading that
//! passed the NE43, stuck and jump checks cannot be detected (bit 16 says
//! the normal rests on three sensors).

use perpend_core::ext::{Context, Prepared};
use perpend_core::normal::{measure_with, prepare};
use perpend_core::params::Params;
use perpend_core::surface::{self, Shape};

use crate::acq::{common_changes, convert, Channel, Class, Conversion};
use crate::status::{
    sensor_bits, CONFIG_INVALID, DEGRADED, NO_PLANE, RESIDUAL_HIGH, SENSOR_STUCK, SENSOR_VALID,
    UNCALIBRATED,
};

/// Number of channels.
pub const CHANNELS: usize = 4;

/// One scan of the ADC and its context.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Sample {
    /// Oversampled ADC result of each channel, in scan order.
    pub counts: [u16; CHANNELS],
    /// Head temperature [°C] as the thermal extension sees it, if
    /// measured ([`crate::app::App::on_sample`] passes the die temperature
    /// through the head's thermal lag, [`crate::thermal`]).
    pub temp_c: Option<f32>,
    /// Time since the start of the run [s] (drift extension), if known.
    pub t_s: Option<f32>,
}

/// The result of one sample (see the module docs for the invalid policy).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Output {
    /// Status word (object 0x2005, [`crate::status`]).
    pub status: u32,
    /// Converted distance of each channel [mm].
    pub readings_mm: [f32; CHANNELS],
    /// Unit normal towards the head (TCS), zero when invalid.
    pub normal: [f32; 3],
    /// Tian θ1 [deg].
    pub theta1_deg: f32,
    /// Tian θ2 [deg].
    pub theta2_deg: f32,
    /// Tian θ [deg].
    pub theta_deg: f32,
    /// Chen pitch (rotation about TCS x) [deg].
    pub pitch_deg: f32,
    /// Chen yaw (rotation about TCS y) [deg].
    pub yaw_deg: f32,
    /// Plane RMS residual [mm] (0 for three sensors).
    pub rms_mm: f32,
}

impl Output {
    /// Whether the output is a valid measurement ([`NO_PLANE`] clear).
    pub const fn valid(&self) -> bool {
        self.status & NO_PLANE == 0
    }

    /// Number of sensors used (valid bits set).
    pub const fn used(&self) -> u32 {
        (self.status & 0x1111).count_ones()
    }
}

/// The pipeline: parameters and per-channel detector state.
#[derive(Debug, Clone)]
pub struct Pipeline {
    params: Params,
    /// The sensors' extensions of `params` prepared for the inversion
    /// (`perpend_core::normal::prepare`): built with `params` in
    /// [`Pipeline::new`], the only place they are set.
    prep: [Prepared<f32>; CHANNELS],
    calibrated: bool,
    config_ok: bool,
    chans: [Channel; CHANNELS],
    shape: Shape<f32>,
}

/// What step 2 yields, whichever surface model: the normal, the angles
/// and the residual.
struct Fitted {
    degraded: bool,
    rms: f32,
    vals: [f32; 9],
}

impl Pipeline {
    /// A pipeline on `params`; `calibrated` is false for factory defaults
    /// (sets [`UNCALIBRATED`]). Parameters that fail
    /// [`Params::validate`] make every output [`CONFIG_INVALID`].
    pub fn new(params: Params, calibrated: bool) -> Self {
        Self {
            config_ok: params.validate().is_ok(),
            prep: prepare(&params.head),
            params,
            calibrated,
            chans: [Channel::default(); CHANNELS],
            shape: Shape::Plane,
        }
    }

    /// The surface model in use ([`Shape::Plane`] unless set).
    pub fn shape(&self) -> Shape<f32> {
        self.shape
    }

    /// Sets the surface model applied to every sample (object 0x2310);
    /// the detector history is kept. [`Shape::Plane`] is the micro-plane,
    /// unchanged in result and cost.
    pub fn set_shape(&mut self, shape: Shape<f32>) {
        self.shape = shape;
    }

    /// The parameters in use.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Whether a calibration (not the factory head) is in use.
    pub fn calibrated(&self) -> bool {
        self.calibrated
    }

    /// Whether the parameters passed [`Params::validate`].
    pub fn config_ok(&self) -> bool {
        self.config_ok
    }

    /// Replaces the parameters and forgets the detector history (the
    /// surface model stays).
    pub fn set_params(&mut self, params: Params, calibrated: bool) {
        let shape = self.shape;
        *self = Self::new(params, calibrated);
        self.shape = shape;
    }

    /// Keeps the parameters but marks them invalid (the dictionary holds a
    /// combination that does not validate): every output has
    /// [`CONFIG_INVALID`] and [`NO_PLANE`] until the next
    /// [`Pipeline::set_params`].
    pub fn invalidate(&mut self, calibrated: bool) {
        self.config_ok = false;
        self.calibrated = calibrated;
        self.chans = [Channel::default(); CHANNELS];
    }

    /// Processes one sample.
    pub fn process(&mut self, s: &Sample) -> Output {
        let p = &self.params;
        let mut out = Output::default();
        if !self.calibrated {
            out.status |= UNCALIBRATED;
        }
        let conv: [Conversion; CHANNELS] =
            core::array::from_fn(|i| convert(s.counts[i], &p.transfer[i], &p.acq));
        for (o, c) in out.readings_mm.iter_mut().zip(conv.iter()) {
            *o = c.mm;
        }
        if !self.config_ok {
            out.status |= CONFIG_INVALID | NO_PLANE;
            return out;
        }

        // Changes since the previous sample, for the jump detector.
        let deltas: [Option<f32>; CHANNELS] = core::array::from_fn(|i| {
            if conv[i].class == Class::Valid {
                self.chans[i].delta(conv[i].mm)
            } else {
                None
            }
        });
        let common = common_changes(&deltas);
        let mut readings: [Option<f32>; CHANNELS] = [None; CHANNELS];
        for i in 0..CHANNELS {
            let c = &conv[i];
            let ch = &mut self.chans[i];
            if c.class != Class::Valid {
                ch.reset();
                out.status |= sensor_bits(i, c.class.bit());
                continue;
            }
            let excess = deltas[i].zip(common[i]).map(|(d, m)| d - m);
            let stuck = ch.stuck(s.counts[i], &p.acq);
            let jumped = ch.jump(c.mm, excess, &p.acq);
            if stuck {
                out.status |= SENSOR_STUCK;
            } else if !jumped {
                readings[i] = Some(c.mm);
                out.status |= sensor_bits(i, SENSOR_VALID);
            }
        }

        let ctx = Context {
            temp_c: s.temp_c.filter(|t| t.is_finite()),
            t_s: s.t_s.filter(|t| t.is_finite()),
        };
        let Some(f) = self.fit(&readings, &ctx) else {
            out.status |= NO_PLANE;
            return out;
        };
        if f.degraded {
            out.status |= DEGRADED;
        } else if !(f.rms <= p.acq.max_rms_mm) {
            out.status |= RESIDUAL_HIGH | NO_PLANE;
            return out;
        }
        let vals = f.vals;
        if !all_finite(&vals) {
            out.status |= NO_PLANE;
            return out;
        }
        out.normal = [vals[0], vals[1], vals[2]];
        out.theta1_deg = vals[3];
        out.theta2_deg = vals[4];
        out.theta_deg = vals[5];
        out.pitch_deg = vals[6];
        out.yaw_deg = vals[7];
        out.rms_mm = vals[8];
        out
    }

    /// Step 2: readings → normal, angles, residual on the surface model
    /// (`None`: any error of the core).
    fn fit(&self, readings: &[Option<f32>; CHANNELS], ctx: &Context<f32>) -> Option<Fitted> {
        let p = &self.params;
        debug_assert!(self.prep == prepare(&p.head), "stale prepared extensions");
        let (degraded, normal, dev, att, rms) = match &self.shape {
            Shape::Plane => {
                let m = measure_with(&p.head, &self.prep, readings, ctx, p.acq.method).ok()?;
                let pl = m.plane;
                (pl.degraded, pl.normal, m.deviation, m.attitude, pl.rms)
            }
            shape => {
                let m =
                    surface::measure_with(&p.head, &self.prep, readings, ctx, p.acq.method, shape)
                        .ok()?;
                let f = m.fit;
                (f.plane.degraded, f.normal, m.deviation, m.attitude, f.rms)
            }
        };
        Some(Fitted {
            degraded,
            rms,
            vals: [
                normal.x,
                normal.y,
                normal.z,
                dev.theta1.to_degrees(),
                dev.theta2.to_degrees(),
                dev.theta.to_degrees(),
                att.pitch.to_degrees(),
                att.yaw.to_degrees(),
                rms,
            ],
        })
    }
}

/// Test helpers shared by the fault-matrix tests.
/// Whether every value is finite: `v·0` is `±0` for a finite `v` and NaN
/// for an infinite or NaN one, so the sum of them is zero exactly when all
/// are finite (a multiply-add per value instead of an integer test and a
/// branch: 48 → ≈ 20 instructions for the nine outputs, `cargo xtask
/// mcu-bench`).
#[inline]
fn all_finite(vals: &[f32]) -> bool {
    vals.iter().fold(0.0f32, |a, v| a + v * 0.0) == 0.0
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
pub(crate) mod testutil {
    use super::*;
    use crate::acq::{counts_for_signal, signal_for_mm};
    use nalgebra::Vector3;
    use perpend_core::geometry::Plane;
    use perpend_core::model::distance;

    /// A calibrated pipeline on the factory parameters.
    pub(crate) fn pipeline() -> Pipeline {
        Pipeline::new(Params::factory(), true)
    }

    /// Distances [mm] of the four sensors looking at `plane` (f64 geometry).
    pub(crate) fn mm_for_plane(p: &Params, plane: &Plane<f64>) -> [f32; 4] {
        let head = p.head.cast::<f64>();
        core::array::from_fn(|i| distance(&head.sensors[i], plane, i).unwrap() as f32)
    }

    /// ADC counts for distances [mm].
    pub(crate) fn counts_for_mm(p: &Params, mm: [f32; 4]) -> [u16; 4] {
        core::array::from_fn(|i| {
            let t = &p.transfer[i];
            counts_for_signal(signal_for_mm(mm[i], t), t, &p.acq)
        })
    }

    /// ADC counts of the four sensors looking at `plane`.
    pub(crate) fn counts_for_plane(p: &Params, plane: &Plane<f64>) -> [u16; 4] {
        counts_for_mm(p, mm_for_plane(p, plane))
    }

    /// ADC counts for a loop current [mA] on channel `i`.
    pub(crate) fn counts_for_ma(p: &Params, i: usize, ma: f32) -> u16 {
        counts_for_signal(ma, &p.transfer[i], &p.acq)
    }

    /// The plane of `perpend demo`.
    pub(crate) fn test_plane() -> Plane<f64> {
        Plane::from_abcd(0.035, -0.052, 1.0, -40.0).unwrap()
    }

    /// A sample of counts without context.
    pub(crate) fn sample(counts: [u16; 4]) -> Sample {
        Sample {
            counts,
            ..Sample::default()
        }
    }

    /// The angle [deg] between the output normal and the plane's.
    pub(crate) fn normal_error_deg(o: &Output, plane: &Plane<f64>) -> f64 {
        let n = Vector3::new(o.normal[0] as f64, o.normal[1] as f64, o.normal[2] as f64);
        (n.dot(&-plane.n)).clamp(-1.0, 1.0).acos().to_degrees()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::testutil::*;
    use super::*;

    /// `all_finite` agrees with `f32::is_finite` on every special value, in
    /// every position, the largest finite values and both zeros included.
    #[test]
    fn all_finite_is_is_finite() {
        let specials = [
            0.0,
            -0.0,
            1.0,
            -3.5e-40,
            f32::MAX,
            f32::MIN,
            f32::MIN_POSITIVE,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ];
        for &x in &specials {
            for pos in 0..9 {
                let mut v = [f32::MAX, -1.0, 2.0, f32::MIN, 0.5, 7.0, -0.0, 1e30, 3.0];
                v[pos] = x;
                assert_eq!(
                    all_finite(&v),
                    v.iter().all(|a| a.is_finite()),
                    "{x} at {pos}"
                );
            }
        }
        assert!(all_finite(&[]));
        assert!(!all_finite(&[f32::INFINITY, f32::NEG_INFINITY]));
    }
    use crate::acq::{counts_for_signal, signal_for_mm};
    use approx::assert_relative_eq;
    use perpend_core::geometry::Plane;
    use perpend_core::normal::Method;
    use proptest::prelude::*;

    #[test]
    fn golden_plane_through_the_adc() {
        let mut pl = pipeline();
        let plane = test_plane();
        let c = counts_for_plane(pl.params(), &plane);
        let o = pl.process(&sample(c));
        assert!(o.valid());
        assert_eq!(o.status, 0x1111);
        assert_eq!(o.used(), 4);
        // 12-bit quantisation (one count = 0.018 mm at 150 Ω over 60 mm)
        // over a ~90 mm spot pattern: well below 0.05°.
        assert!(normal_error_deg(&o, &plane) < 0.05, "{o:?}");
        // θ from eq. 4: atan(|n_xy| / |n_z|)
        let want = (0.035f64.hypot(0.052)).atan().to_degrees();
        assert_relative_eq!(o.theta_deg as f64, want, epsilon = 0.05);
        assert!(o.rms_mm < 0.02);
        for r in o.readings_mm {
            assert!(r > 40.0 && r < 55.0);
        }
    }

    #[test]
    fn uncalibrated_flag_does_not_invalidate() {
        let mut pl = Pipeline::new(Params::factory(), false);
        let o = pl.process(&sample(counts_for_plane(pl.params(), &test_plane())));
        assert!(o.valid());
        assert_eq!(o.status, UNCALIBRATED | 0x1111);
    }

    #[test]
    fn invalid_config_never_valid() {
        let mut p = Params::factory();
        p.acq.max_rms_mm = -1.0;
        let mut pl = Pipeline::new(p, true);
        assert!(!pl.config_ok());
        let o = pl.process(&sample([2000; 4]));
        assert_eq!(o.status, CONFIG_INVALID | NO_PLANE);
        assert_eq!(o.normal, [0.0; 3]);
    }

    #[test]
    fn chen_method_agrees() {
        let mut p = Params::factory();
        p.acq.method = Method::Chen;
        let mut pl = Pipeline::new(p, true);
        let plane = test_plane();
        let o = pl.process(&sample(counts_for_plane(pl.params(), &plane)));
        assert!(o.valid());
        assert!(normal_error_deg(&o, &plane) < 0.05);
    }

    #[test]
    fn thermal_extension_uses_temperature() {
        let mut p = Params::factory();
        p.head.sensors[0].ext.thermal = 0.05; // 50 µm/°C on sensor 1
                                              // At 30 °C sensor 1 reads 0.5 mm long.
        let plane = test_plane();
        let mut mm = mm_for_plane(&p, &plane);
        mm[0] += 0.5;
        let counts = counts_for_mm(&p, mm);
        let mut pl = Pipeline::new(p, true);
        let with_t = pl.process(&Sample {
            counts,
            temp_c: Some(30.0),
            t_s: None,
        });
        assert!(with_t.valid(), "{with_t:?}");
        assert!(normal_error_deg(&with_t, &plane) < 0.05);
        // Without the temperature the 0.5 mm error shows as a residual.
        let mut pl2 = Pipeline::new(p, true);
        let without = pl2.process(&sample(counts));
        assert_eq!(
            without.status & (RESIDUAL_HIGH | NO_PLANE),
            RESIDUAL_HIGH | NO_PLANE
        );
        // A NaN temperature is ignored rather than propagated.
        let mut pl3 = Pipeline::new(p, true);
        let nan_t = pl3.process(&Sample {
            counts,
            temp_c: Some(f32::NAN),
            t_s: Some(f32::INFINITY),
        });
        assert_eq!(nan_t.status, without.status);
    }

    #[test]
    fn voltage_channel_in_the_mix() {
        let mut p = Params::factory();
        p.transfer[2] = perpend_core::params::Transfer::voltage(0.3, 20.0, 80.0);
        let plane = test_plane();
        let mm = mm_for_plane(&p, &plane);
        let counts: [u16; 4] = core::array::from_fn(|i| {
            let t = &p.transfer[i];
            counts_for_signal(signal_for_mm(mm[i], t), t, &p.acq)
        });
        let mut pl = Pipeline::new(p, true);
        let o = pl.process(&sample(counts));
        assert!(o.valid());
        assert!(normal_error_deg(&o, &plane) < 0.05);
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

        /// Any ADC input: outputs finite; valid => unit normal and small residual.
        #[test]
        fn never_nan_and_valid_means_unit(counts in prop::array::uniform4(any::<u16>()), n in 1usize..4) {
            let mut pl = pipeline();
            let mut o = Output::default();
            for _ in 0..n {
                o = pl.process(&sample(counts));
            }
            let angles = [o.theta1_deg, o.theta2_deg, o.theta_deg, o.pitch_deg, o.yaw_deg, o.rms_mm];
            for v in o.normal.iter().chain(o.readings_mm.iter()).chain(angles.iter()) {
                prop_assert!(v.is_finite());
            }
            if o.valid() {
                let len = o.normal.iter().map(|v| v * v).sum::<f32>().sqrt();
                prop_assert!((len - 1.0).abs() < 1e-4);
                prop_assert!(o.rms_mm <= pl.params().acq.max_rms_mm);
                prop_assert!(o.used() >= 3);
            } else {
                prop_assert_eq!(o.normal, [0.0; 3]);
            }
        }

        /// Tilted planes within ±10°: valid and within 0.05° of the truth.
        #[test]
        fn tilted_planes(a in -0.17f64..0.17, b in -0.17f64..0.17, d in 35.0f64..50.0) {
            let plane = Plane::from_abcd(a, b, 1.0, -d).unwrap();
            let mut pl = pipeline();
            let o = pl.process(&sample(counts_for_plane(pl.params(), &plane)));
            prop_assert!(o.valid(), "{:?}", o);
            prop_assert!(normal_error_deg(&o, &plane) < 0.05);
        }
    }
}

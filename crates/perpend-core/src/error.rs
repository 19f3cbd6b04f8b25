//! The one error type of `perpend-core`.
//!
//! Every public function that can be handed bad input returns
//! [`Error`] instead of panicking or producing a NaN. Variants carry only
//! `'static` names and small integers so the type stays `Copy` and fits the
//! board.

use core::fmt;

/// Everything that can go wrong in the measurement core.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum Error {
    /// An input value was NaN or infinite; the payload names the input.
    NonFinite(&'static str),
    /// A direction (beam direction, plane normal) had zero or near-zero
    /// length and cannot be normalised; the payload names it.
    ZeroLength(&'static str),
    /// The beam of sensor `.0` (0-based) is parallel, or within the numeric
    /// tolerance of parallel, to the plane: it never meets it (Chen eq. 1-2
    /// have no intersection).
    BeamParallelToPlane(usize),
    /// The plane lies behind sensor `.0` (0-based): the intersection is at a
    /// negative distance along the beam.
    PlaneBehindSensor(usize),
    /// Sensor `.0` (0-based) reported a negative distance; distances are
    /// measured from the zero point along the beam and cannot be negative.
    NegativeDistance(usize),
    /// Fewer than three valid readings: a plane needs three points. The
    /// payload is the number of valid readings.
    TooFewReadings(usize),
    /// The spot points are (nearly) collinear or coincident, so they do not
    /// define a plane.
    DegenerateSpots,
    /// The measured surface faces away from the spindle (its normal has a
    /// component along +z feed towards the head side): no deviation angle is
    /// defined. Happens only with a head model that is badly wrong.
    SurfaceFacesAway,
    /// A rotation matrix handed to an Euler decomposition is not orthonormal
    /// within tolerance.
    NotARotation,
    /// A configuration value is out of its documented range; the payload
    /// names the value.
    OutOfRange(&'static str),
    /// The calibration pose set cannot identify the parameters of sensor
    /// `.0` (0-based): the normal matrix is singular or too ill-conditioned.
    NotIdentifiable(usize),
    /// An iterative solver did not converge within its iteration budget.
    NoConvergence,
    /// A parameter record could not be decoded; the payload names the reason.
    Decode(&'static str),
    /// An output buffer was too small for the encoded record.
    BufferTooSmall,
    /// The spindle axis does not meet the fitted curved surface: it passes
    /// beside the sphere or cylinder, or runs parallel to the cylinder's
    /// axis ([`crate::surface`]), so there is no point to take the normal at.
    AxisMissesSurface,
    /// The surface's radius is too small for the spread of the spots
    /// ([`crate::surface`]): a spot lies farther from the spot pattern's
    /// centre, across the surface, than half the radius (30° of arc), where
    /// the nominal shape is not a height field over the micro-plane that
    /// starts the fit.
    SurfaceTooCurved,
    /// The beam of sensor `.0` (0-based) misses the curved surface
    /// ([`crate::surface::CurvedSurface::distance`]).
    BeamMissesSurface(usize),
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::NonFinite(w) => write!(f, "{w} is NaN or infinite"),
            Error::ZeroLength(w) => write!(f, "{w} has zero length"),
            Error::BeamParallelToPlane(i) => {
                write!(f, "beam of sensor {} is parallel to the plane", i + 1)
            }
            Error::PlaneBehindSensor(i) => {
                write!(f, "plane lies behind sensor {}", i + 1)
            }
            Error::NegativeDistance(i) => {
                write!(f, "sensor {} reported a negative distance", i + 1)
            }
            Error::TooFewReadings(n) => {
                write!(f, "{n} valid readings; a plane needs at least 3")
            }
            Error::DegenerateSpots => write!(f, "spot points are collinear or coincident"),
            Error::SurfaceFacesAway => write!(f, "surface faces away from the spindle"),
            Error::NotARotation => write!(f, "matrix is not a rotation"),
            Error::OutOfRange(w) => write!(f, "{w} is out of range"),
            Error::NotIdentifiable(i) => write!(
                f,
                "pose set cannot identify the parameters of sensor {}",
                i + 1
            ),
            Error::NoConvergence => write!(f, "solver did not converge"),
            Error::Decode(w) => write!(f, "cannot decode parameter record: {w}"),
            Error::BufferTooSmall => write!(f, "output buffer too small"),
            Error::AxisMissesSurface => {
                write!(f, "the spindle axis does not meet the fitted surface")
            }
            Error::BeamMissesSurface(i) => {
                write!(f, "beam of sensor {} misses the surface", i + 1)
            }
            Error::SurfaceTooCurved => write!(
                f,
                "surface radius too small for the spot spread (a spot beyond half the radius)"
            ),
        }
    }
}

#[cfg(any(test, feature = "std"))]
impl std::error::Error for Error {}

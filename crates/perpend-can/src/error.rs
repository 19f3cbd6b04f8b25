//! The crate's error type (the bus itself only sees SDO abort codes, see
//! [`crate::sdo::SdoAbort`]).

use core::fmt;

/// Errors of the application-facing API.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Error {
    /// A persistence image has the wrong length (`expected`, `got`).
    ImageLength {
        /// [`crate::IMAGE_LEN`].
        expected: usize,
        /// The length passed in.
        got: usize,
    },
    /// A persistence image was written by a different dictionary layout
    /// (firmware with other persisted objects): it is ignored as a whole.
    ImageLayout,
    /// A value of a persistence image or parameter record is outside its
    /// object's limits, or a sensor's linearity table is active with knots
    /// not strictly ascending (reported as sub 16 of its object): a
    /// corrupted or forged record; nothing was loaded.
    Value {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// [`crate::Device::finish_request`] without a pending request.
    NoRequest,
}

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Error::ImageLength { expected, got } => {
                write!(f, "parameter image has {got} bytes, expected {expected}")
            }
            Error::ImageLayout => write!(
                f,
                "parameter image was written by another object dictionary layout"
            ),
            Error::Value { index, sub } => {
                write!(f, "stored value of {index:#06x} sub {sub} is out of range")
            }
            Error::NoRequest => write!(f, "no store or restore request is pending"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for Error {}

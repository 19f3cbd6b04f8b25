//! The diagnosis side of the host tool, as a library, at the top of the
//! host layers (above `perpend-calib`, which is above `perpend-formats`):
//! the diagnosis stages ([`diagnose`]), the study of the paper
//! ([`diagnose::study`]) and the benchmarks ([`bench`]). Transitional
//! facade: it re-exports the modules of `perpend-formats` and
//! `perpend-calib` under their former paths (`perpend_lab::exchange`,
//! `perpend_lab::calibrate`, `perpend_lab::diagnose::noise`, …) so that
//! the binary (`perpend-cli`) and the tests keep their imports while they
//! move to the new crates; it adds no code to them.
//!
//! Each command's options are a struct deriving `clap::Args` beside its
//! `run`, so that the binary and the host tests drive the same code.
#![deny(missing_docs)]

pub mod bench;
pub mod diagnose;

pub use perpend_calib::{
    accuracy, calibrate, cellconfig, curvature, frames, interim, measure, plan, record, sim,
};
pub use perpend_formats::{conformity, exchange, paramfile, plausible, progress, schema};

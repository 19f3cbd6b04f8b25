//! The diagnosis side of the host tool, as a library, at the top of the
//! host layers (above `perpend-calib`, which is above `perpend-formats`):
//! the diagnosis stages ([`diagnose`]), the study of the paper
//! ([`diagnose::study`]) and the benchmarks ([`bench`]). It reads the
//! exchange files through `perpend-formats`, calibrates and re-simulates
//! through `perpend-calib` (whose shared statistics, noise from the data,
//! outliers, folds and cross-validation, it uses as they are), and adds
//! what only the diagnosis needs: the candidate fits and scores, the
//! decision, detection limits, the report and the study. Nothing below it
//! imports it; Cargo enforces the direction.
//!
//! Each command's options are a struct deriving `clap::Args` beside its
//! `run`, so that the binary and the host tests drive the same code.
#![deny(missing_docs)]

pub mod bench;
pub mod diagnose;

//! The `perpend` host tool as a library, so that host tests drive the same
//! code as the command line.
//!
//! Each subcommand lives in its own module with its `Args` (clap) and `run`.
#![deny(missing_docs)]

pub mod bench;
pub mod board;
pub mod calibrate;
pub mod demo;
pub mod diagnose;
pub mod exchange;
pub mod paramfile;
pub mod sim;
pub mod slcan;

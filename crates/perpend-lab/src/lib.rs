//! The analysis side of the host tool, as a library: the exchange format,
//! the simulator, the calibration driver, the diagnosis, the measurement
//! of readings files, the study of the paper and the benchmarks. No CAN,
//! no terminal beyond the reports each entry point prints: the `perpend`
//! binary (`perpend-cli`) wires these into commands and adds the virtual
//! board and the CAN transports.
//!
//! Each command's options are a struct deriving `clap::Args` beside its
//! `run`, so that the binary and the host tests drive the same code.
#![deny(missing_docs)]

pub mod accuracy;
pub mod bench;
pub mod calibrate;
pub mod cellconfig;
pub mod conformity;
pub mod curvature;
pub mod diagnose;
pub mod exchange;
pub mod frames;
pub mod interim;
pub mod measure;
pub mod paramfile;
pub mod plan;
pub mod plausible;
pub mod progress;
pub mod record;
pub mod schema;
pub mod sim;

//! The calibration side of the host tool, as a library, above
//! `perpend-formats` and below the diagnosis (`perpend-diagnosis`): the
//! simulator ([`sim`]), the calibration driver ([`calibrate`]) with the
//! robust statistics every calibration runs and the diagnosis shares (the
//! candidate models and their fits [`candidates`], outliers and the noise
//! from the data [`noise`], the residual moments [`moments`], folds
//! [`folds`], cross-validation [`cv`], the sensor time constants [`lags`],
//! small statistics [`stats`]), the calibration record ([`record`]),
//! planning ([`plan`]), the robot and tracker frames ([`frames`]),
//! curvature ([`curvature`]), the measurement of readings files
//! ([`measure`]), the expected normal error ([`accuracy`]), the cell
//! configuration ([`cellconfig`]) and the interim checks ([`interim`]). It
//! imports nothing from the diagnosis.
//!
//! Each command's options are a struct deriving `clap::Args` beside its
//! `run`, so that the binary and the host tests drive the same code.
#![deny(missing_docs)]

pub mod accuracy;
pub mod calibrate;
pub mod candidates;
pub mod cellconfig;
pub mod curvature;
pub mod cv;
pub mod folds;
pub mod frames;
pub mod interim;
pub mod lags;
pub mod measure;
pub mod moments;
pub mod noise;
pub mod plan;
pub mod record;
pub mod sim;
pub mod stats;

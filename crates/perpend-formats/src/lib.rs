//! The files the host tool reads and writes, as a library, at the bottom of
//! the host layers: the exchange format of runs (`sensors.csv`,
//! `poses.csv`, readings, [`exchange`]) and the physical plausibility of
//! what it reads ([`plausible`]), the parameter file a board is loaded
//! with ([`paramfile`]), the JSON schema version and writer every `--json`
//! output shares ([`schema`]), the conformity decision against a stated
//! tolerance ([`conformity`]) and the terminal progress bar of the long
//! commands ([`progress`]). It computes no calibration and no diagnosis:
//! `perpend-calib` and `perpend-diagnosis` (the diagnosis) build on it, never the
//! reverse.
#![deny(missing_docs)]

pub mod conformity;
pub mod exchange;
pub mod paramfile;
pub mod plausible;
pub mod progress;
pub mod schema;

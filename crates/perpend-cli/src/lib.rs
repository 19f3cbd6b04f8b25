//! The `perpend` binary as a library: the commands that are not analysis
//! (the demo, the virtual board, the CAN buses and the CANopen master of
//! `perpend node`), so that host tests drive the same code as the command
//! line. The analysis commands live in `perpend-diagnosis`.
#![deny(missing_docs)]

pub mod board;
pub mod bus;
pub mod canopen;
pub mod cell;
pub mod demo;
pub mod eds;
pub mod node;
pub mod pipe;
pub mod progress;
pub mod record;
pub mod record_cert;
pub mod record_fmt;
pub mod record_history;
pub mod schema;
pub mod slcan;

//! The firmware's board modules (`src/*.rs` of perpend-fw, included as
//! they are) for the on-target tests in `tests/board.rs`: what those tests
//! exercise is the code the firmware runs, not a copy.
//!
//! `cargo xtask hil` builds the tests and runs them with `probe-rs run
//! --chip STM32G474RETx` (NUCLEO-G474RE, no CAN transceiver needed: the
//! FDCAN runs in internal loopback).

#![no_std]

#[path = "../../src/acq_ctl.rs"]
pub mod acq_ctl;
#[path = "../../src/board.rs"]
pub mod board;
#[path = "../../src/can_rx.rs"]
pub mod can_rx;
#[path = "../../src/can_tx.rs"]
pub mod can_tx;
#[path = "../../src/flash.rs"]
pub mod flash;

use defmt_rtt as _;

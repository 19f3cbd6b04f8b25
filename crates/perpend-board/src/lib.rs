//! # perpend-board
//!
//! The board logic of the perpend sensor board, free of any HAL so that the
//! firmware and the host (tests, the virtual board of `perpend-cli`) run the
//! same code:
//!
//! * [`acq`] — ADC counts → mA/V → mm, NAMUR NE43 classes, stuck and jump
//!   detectors;
//! * [`pipeline`] — four ADC results → status, normal, θ1/θ2/θ, pitch/yaw,
//!   residual (through `perpend_core::normal::measure` in `f32`);
//! * [`storage`] — the parameter record in flash through `sequential-storage`,
//!   boot-time loading with factory fallback, a fault-injecting flash;
//! * [`status`] — the status-word bits;
//! * [`app`] — [`app::App`]: pipeline + storage + the CANopen device of
//!   `perpend-can`, frames in / frames out, time passed in;
//! * [`txq`] — the software transmit queue in CAN priority order between
//!   the application and the controller (never blocks the acquisition);
//! * [`bittiming`] — the FDCAN nominal bit timing of the four bit rates;
//! * [`bootctl`] — the ROM-loader request in a backup register, the IWDG
//!   hand-over from the bootloader, the option-byte check;
//! * [`health`] — reset cause, VREF+ from VREFINT, die temperature, flash
//!   layout check, worst loop time, stack high-water mark;
//! * [`rxfilter`] — the FDCAN receive acceptance filters and a model of the
//!   receive path (FIFOs, interrupt ring) around a flash store;
//! * [`thermal`] — the head temperature through the thermal time constant
//!   (0x2105) for the thermal extension;
//! * [`fdcan`] — the FDCAN transmit-buffer logic and the run-time bit-rate
//!   switch over a register trait;
//! * [`busmon`] — bus errors and bus-off from one PSR read per tick, the
//!   main loop's receive budget and event order;
//! * [`ecc`] — a storage read that sees every ECC error (flags cleared,
//!   data cache bypassed, NMI offsets substituted);
//! * [`program`] — CiA 302-3 program download (0x1F50/0x1F51/0x1F56/
//!   0x1F57) into a program store (a RAM fake on the host);
//! * [`image`] — signed firmware images: embassy-boot's ed25519 signature
//!   plus an identity trailer (product code, version, SHA-256);
//! * [`scan`] — the ADC scan time and the shortest sample period an
//!   oversampling ratio allows.
//!
//! `no_std`, no allocator; every buffer is sized in its type.
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![deny(missing_docs)]

pub mod acq;
pub mod app;
pub mod bittiming;
pub mod bootctl;
pub mod busmon;
pub mod capture;
pub mod confirm;
#[cfg(test)]
mod confirm_app_tests;
#[cfg(any(test, feature = "dfu"))]
pub mod dfu;
#[cfg(test)]
mod dfu_tests;
pub mod ecc;
pub mod fdcan;
pub mod health;
#[cfg(test)]
mod health_tests;
pub mod image;
pub mod pipeline;
pub mod program;
pub mod rxfilter;
pub mod scan;
pub mod status;
pub mod storage;
pub mod thermal;
pub mod txq;

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod fault_matrix;

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "flash_fault_tests.rs"]
mod flash_fault_tests;

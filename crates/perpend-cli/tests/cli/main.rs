//! The integration tests of the `perpend` binary, one test binary (each file
//! a module: one link instead of seventeen). `cargo test -p perpend-cli --test cli
//! cell::` runs one file's tests.

mod common;
mod support;

mod args_order;
mod cell;
mod cell_faults;
mod cell_frames;
mod closed_stdout;
mod corpus_commands;
mod extensions_stored;
mod help;
mod hidden_effects;
mod json_node;
mod lss;
mod measure;
mod node;
mod plan;
mod record;
mod sdo;
mod update;

//! The integration tests of the diagnosis library, one test binary (each file
//! a module: one link instead of nine). `cargo test -p perpend-diagnosis --test
//! diagnosis study_doc::` runs one file's tests.

mod calibration;
mod diagnose_direction;
mod diagnose_end_to_end;
mod diagnose_golden;
mod diagnose_limits;
mod diagnose_normal_cost;
mod diagnose_time_pair;
mod json_schema;
mod study_doc;

//! The exchange-format CSV readers (`sensors.csv`, `poses.csv`) on
//! arbitrary bytes: they return a table or an error naming file and line,
//! never panic; a table they accept holds only finite numbers.
#![no_main]
use libfuzzer_sys::fuzz_target;
use perpend_formats::exchange::{parse_poses, parse_sensors};

fuzz_target!(|data: &[u8]| {
    if let Ok(t) = parse_sensors(data, "sensors.csv") {
        for s in t.sensors().into_iter().flatten() {
            assert!(s.zero.iter().chain(s.dir.iter()).all(|x| x.is_finite()));
        }
    }
    let _ = parse_poses(data, "poses.csv", None);
    let _ = parse_poses(data, "poses.csv", Some(4));
});

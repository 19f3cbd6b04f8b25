//! The host tool's other parsers on arbitrary bytes: the slcan lines an
//! adapter sends to `perpend node` (with and without timestamps), the
//! `--bus` specification, the readings file of `perpend measure`, and the
//! calibration records, interim check records and cell configurations
//! that `perpend record` and `perpend cell` read.
//! Each returns a value or an error, never panics; a frame it accepts is
//! well-formed.
#![no_main]
use libfuzzer_sys::fuzz_target;
use perpend_calib::cellconfig::CellConfig;
use perpend_calib::interim::CheckRecord;
use perpend_calib::record::Record;
use perpend_cli::bus::slcan::{parse_line, Line};
use perpend_cli::bus::BusSpec;
use perpend_formats::exchange::parse_readings;

fuzz_target!(|data: &[u8]| {
    for line in data.split(|b| *b == b'\r') {
        if let Line::Frame(f) = parse_line(line) {
            assert!(f.is_well_formed());
        }
    }
    if let Ok(s) = std::str::from_utf8(data) {
        let _ = s.parse::<BusSpec>();
        let _ = Record::parse(s, "record.json");
        let _ = CheckRecord::parse(s, "check.json");
        let _ = CellConfig::parse(s, "cell-config.json");
    }
    let _ = parse_readings(data, "readings.csv", None);
    let _ = parse_readings(data, "readings.csv", Some(4));
});

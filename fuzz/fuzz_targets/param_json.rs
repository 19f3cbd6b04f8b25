//! The calibration parameter JSON reader on arbitrary text: a parameter file
//! or an error, never a panic; an accepted file validates and yields finite
//! sensors.
#![no_main]
use libfuzzer_sys::fuzz_target;
use perpend_formats::paramfile::ParamFile;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        if let Ok(p) = ParamFile::parse(text, "params.json") {
            assert!(p.validate().is_ok());
            if let Ok(sensors) = p.sensors() {
                for s in sensors {
                    assert!(s.zero.iter().chain(s.dir.iter()).all(|x| x.is_finite()));
                }
            }
        }
    }
});

//! The board's stored-parameter record decoder on arbitrary bytes: decode
//! never panics, an accepted record validates, and re-encoding it gives a
//! record that decodes to the same value.
#![no_main]
use libfuzzer_sys::fuzz_target;
use perpend_core::params::Params;

fuzz_target!(|data: &[u8]| {
    if let Ok(p) = Params::decode(data) {
        assert!(p.validate().is_ok());
        let mut buf = [0u8; 1024];
        let n = p.encode(&mut buf).expect("an accepted record re-encodes");
        let q = Params::decode(&buf[..n]).expect("a re-encoded record decodes");
        assert_eq!(p, q);
    }
});

//! The board's stored-parameter record decoder on arbitrary bytes: decode
//! never panics, an accepted record validates, and re-encoding it gives a
//! record that decodes to the same value.
//!
//! Random bytes almost never carry a valid CRC-32, which would leave the
//! value checks behind it unexplored; so each input is also tried as the
//! payload of a well-formed record (magic, version, length, fixed-up CRC).
#![no_main]
use libfuzzer_sys::fuzz_target;
use perpend_core::params::{crc32, Params, HEADER_LEN, MAGIC, PAYLOAD_LEN, RECORD_LEN, VERSION};

fn check(buf: &[u8]) {
    if let Ok(p) = Params::decode(buf) {
        assert!(p.validate().is_ok());
        let mut out = [0u8; 1024];
        let n = p.encode(&mut out).expect("an accepted record re-encodes");
        let q = Params::decode(&out[..n]).expect("a re-encoded record decodes");
        assert_eq!(p, q);
    }
}

fuzz_target!(|data: &[u8]| {
    check(data);
    let mut rec = [0u8; RECORD_LEN];
    rec[..4].copy_from_slice(&MAGIC);
    rec[4..6].copy_from_slice(&VERSION.to_le_bytes());
    rec[6..8].copy_from_slice(&(PAYLOAD_LEN as u16).to_le_bytes());
    let n = data.len().min(PAYLOAD_LEN);
    rec[HEADER_LEN..HEADER_LEN + n].copy_from_slice(&data[..n]);
    let crc = crc32(&rec[..RECORD_LEN - 4]);
    rec[RECORD_LEN - 4..].copy_from_slice(&crc.to_le_bytes());
    check(&rec);
});

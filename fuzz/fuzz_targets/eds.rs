//! The EDS reader (`perpend node sdo --eds FILE`) on arbitrary text: an
//! error names a line of the text, never a panic; what parses is typed
//! and every entry's limits and unit are printable.
#![no_main]
use libfuzzer_sys::fuzz_target;
use perpend_cli::eds::Eds;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    match Eds::parse("fuzz.eds", &text) {
        Ok(eds) => {
            for e in eds.entries.values() {
                let _ = (e.ty.name(), e.limits_text(), e.access.writable());
                assert!(eds.objects.contains_key(&e.index));
            }
        }
        Err(e) => assert!(e.line <= text.lines().count()),
    }
});

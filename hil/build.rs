//! Puts the firmware's `memory.x` where cortex-m-rt's `link.x` finds it and
//! links the test binary with embedded-test's script (its test table).

use std::env;
use std::fs;
use std::path::PathBuf;

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("OUT_DIR is set by cargo"));
    fs::copy("../src/memory.x", out.join("memory.x")).expect("memory.x of the firmware");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rustc-link-arg-tests=-Tembedded-test.x");
    println!("cargo::rustc-check-cfg=cfg(rust_analyzer)");
    println!("cargo:rerun-if-changed=../src/memory.x");
    println!("cargo:rerun-if-changed=build.rs");
}

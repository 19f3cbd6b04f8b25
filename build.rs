//! Puts `src/memory.x` where the linker (cortex-m-rt's `link.x`) finds it,
//! and asks the linker to fold identical functions. The target-specific
//! link arguments are in `.cargo/config.toml`.
//!
//! Not at the repository root: the linker runs in the workspace root and
//! looks for `memory.x` there before the `-L` paths, so a root `memory.x`
//! would also be taken by the bootloader (`boot/`, its own layout).

use std::env;
use std::fs;
use std::path::PathBuf;

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("OUT_DIR is set by cargo"));
    fs::copy("src/memory.x", out.join("memory.x")).expect("src/memory.x of the firmware");
    println!("cargo:rustc-link-search={}", out.display());
    // Identical code folding: functions that compiled to the same bytes
    // (drop glue, closures, monomorphizations) are kept once (−360 B of
    // flash, `cargo xtask size`; issue 50 item 7).
    println!("cargo:rustc-link-arg-bins=--icf=all");
    println!("cargo:rerun-if-changed=src/memory.x");
    println!("cargo:rerun-if-changed=build.rs");
}

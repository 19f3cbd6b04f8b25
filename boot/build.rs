//! Puts `memory.x` where cortex-m-rt's `link.x` finds it and the public key
//! of the field update into `OUT_DIR/public_key.bin` for `include_bytes!`.
//!
//! The key is `../keys/test-only.pk` (TEST KEY, see keys/README.md) unless
//! `PERPEND_PUBLIC_KEY` names another 32-byte public key file (a release:
//! `PERPEND_PUBLIC_KEY=/path/release.pk cargo xtask fw`). A file that is
//! not 32 bytes stops the build.

use std::env;
use std::fs;
use std::path::PathBuf;

/// The environment variable naming the release public key.
const KEY_VAR: &str = "PERPEND_PUBLIC_KEY";

fn main() -> Result<(), String> {
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("OUT_DIR is set by cargo"));
    fs::copy("memory.x", out.join("memory.x")).expect("memory.x is next to build.rs");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed={KEY_VAR}");

    let (path, test) = match env::var_os(KEY_VAR) {
        Some(p) => (PathBuf::from(p), false),
        None => (PathBuf::from("../keys/test-only.pk"), true),
    };
    println!("cargo:rerun-if-changed={}", path.display());
    let key = fs::read(&path).map_err(|e| {
        format!(
            "{KEY_VAR}: cannot read the public key {}: {e} (give the .pk file of `cargo xtask keygen`)",
            path.display()
        )
    })?;
    if key.len() != 32 {
        return Err(format!(
            "{KEY_VAR}: {} has {} bytes, an ed25519 public key has 32 (the .pk file of `cargo xtask keygen`, not the .sk)",
            path.display(),
            key.len()
        ));
    }
    if test {
        println!(
            "cargo:warning=perpend-boot: built with keys/test-only.pk (TEST KEY, accepts images anyone can sign); set {KEY_VAR} for a release"
        );
    }
    fs::write(out.join("public_key.bin"), key).map_err(|e| format!("OUT_DIR: {e}"))
}

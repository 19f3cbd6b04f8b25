//! Puts `memory.x` where cortex-m-rt's `link.x` finds it and the public key
//! of the field update into `OUT_DIR/public_key.bin` for `include_bytes!`.
//!
//! The key is the file named by `PERPEND_PUBLIC_KEY` (a release:
//! `PERPEND_PUBLIC_KEY=/path/release.pk cargo xtask fw`). Without it the
//! build stops, unless the cargo feature `test-key` asks explicitly for
//! `../keys/test-only.pk` (TEST KEY, see keys/README.md; what `cargo xtask
//! fw --test-key` and CI build): a release never carries the test key by
//! accident. The test key sets `cfg(perpend_test_key)` (the bootloader
//! then says so in its boot info and its RTT log). A file that is not 32
//! bytes stops the build.

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

    println!("cargo:rustc-check-cfg=cfg(perpend_test_key)");
    let test_key_feature = env::var_os("CARGO_FEATURE_TEST_KEY").is_some();
    let (path, test) = match env::var_os(KEY_VAR) {
        Some(p) => (PathBuf::from(p), false),
        None if test_key_feature => (PathBuf::from("../keys/test-only.pk"), true),
        None => {
            return Err(format!(
                "perpend-boot: no public key: set {KEY_VAR}=/path/release.pk for a release, \
                 or build a TEST bootloader explicitly with the feature `test-key` \
                 (`cargo xtask fw --test-key`, `--features perpend-boot/test-key`), \
                 which trusts keys/test-only.pk, a key anyone can sign with"
            ))
        }
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
        println!("cargo:rustc-cfg=perpend_test_key");
        println!(
            "cargo:warning=perpend-boot: built with keys/test-only.pk (TEST KEY, accepts images anyone can sign); set {KEY_VAR} for a release"
        );
    }
    fs::write(out.join("public_key.bin"), key).map_err(|e| format!("OUT_DIR: {e}"))
}

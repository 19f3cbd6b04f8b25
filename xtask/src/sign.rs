//! Signed firmware images for the field update: `cargo xtask fw --sign KEY`
//! and `cargo xtask keygen OUT`.
//!
//! * `fw --sign KEY [--allow-downgrade]` — after the build, the ELF's loadable flash segments
//!   are laid out from the lowest load address (gaps 0xFF, erased flash)
//!   into a binary, and `perpend_board::image::sign` appends the identity
//!   trailer (product code of the board's identity, the workspace version,
//!   SHA-256) and embassy-boot's ed25519 signature of the SHA-512 of the
//!   signed bytes. Written next to the ELF as `perpend-fw.signed.bin`.
//!   `--allow-downgrade` sets the trailer's signed flag that lets a board
//!   running a newer version take this one (versions only go up
//!   otherwise, `perpend_board::image::check_version`).
//! * `keygen OUT` — a new key pair from the OS's random source:
//!   `OUT.sk` (32-byte ed25519 seed, the private key: keep it off the
//!   repository) and `OUT.pk` (32-byte public key, RFC 8032 encoding, the
//!   form embassy-boot takes); refuses to overwrite an existing key.
//!
//! Limits: a key file is the raw 32 bytes (no password, no PEM/signify
//! header); the random source is `/dev/urandom` (Linux, macOS).

use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};

use object::read::elf::{ElfFile32, ProgramHeader};

use perpend_board::image;

type Result<T> = std::result::Result<T, String>;

/// Flash addresses of the STM32G474RE.
const FLASH_RANGE: std::ops::Range<u64> = 0x0800_0000..0x0810_0000;
/// Largest binary accepted [bytes] (the whole flash).
const MAX_BIN: u64 = FLASH_RANGE.end - FLASH_RANGE.start;

/// Reads a 32-byte key file.
pub fn read_key(path: &Path) -> Result<[u8; 32]> {
    let bytes = fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    <[u8; 32]>::try_from(bytes.as_slice()).map_err(|_| {
        format!(
            "{}: {} bytes, a key file holds the 32 raw bytes of an ed25519 key \
             (make one with `cargo xtask keygen OUT`)",
            path.display(),
            bytes.len()
        )
    })
}

/// The flash contents of an ELF: its loadable segments in flash from the
/// lowest load address, gaps filled with 0xFF.
pub fn flash_binary(elf: &[u8]) -> Result<Vec<u8>> {
    let elf =
        ElfFile32::<object::Endianness>::parse(elf).map_err(|e| format!("not an ELF: {e}"))?;
    let endian = elf.endian();
    let mut parts = Vec::new();
    for ph in elf.elf_program_headers() {
        let paddr = u64::from(ph.p_paddr(endian));
        if ph.p_type(endian) != object::elf::PT_LOAD || ph.p_filesz(endian) == 0 {
            continue;
        }
        if FLASH_RANGE.contains(&paddr) {
            let data = ph
                .data(endian, elf.data())
                .map_err(|_| format!("segment at {paddr:#x} lies outside the file"))?;
            parts.push((paddr, data));
        }
    }
    let start = parts
        .iter()
        .map(|p| p.0)
        .min()
        .ok_or("no loadable segment in flash")?;
    let end = parts
        .iter()
        .map(|p| p.0 + p.1.len() as u64)
        .max()
        .unwrap_or(start);
    if end - start > MAX_BIN {
        return Err(format!(
            "flash segments span {} bytes, more than the flash",
            end - start
        ));
    }
    let mut bin = vec![0xFF; (end - start) as usize];
    for (at, data) in parts {
        let o = (at - start) as usize;
        bin[o..o + data.len()].copy_from_slice(data);
    }
    Ok(bin)
}

/// Signs the firmware ELF at `elf` with the seed in `key`: the signed
/// image's path.
pub fn sign_elf(elf: &Path, key: &Path, allow_downgrade: bool) -> Result<PathBuf> {
    let seed = read_key(key)?;
    let data = fs::read(elf).map_err(|e| format!("{}: {e}", elf.display()))?;
    let bin = flash_binary(&data)?;
    let product = perpend_can::Defaults::nominal().identity.product_code;
    let version = perpend_board::program::build_version();
    let flags = if allow_downgrade {
        image::FLAG_ALLOW_DOWNGRADE
    } else {
        0
    };
    let signed = image::sign_with_flags(&bin, product, version, flags, &seed);
    let out = elf.with_file_name("perpend-fw.signed.bin");
    fs::write(&out, &signed).map_err(|e| format!("{}: {e}", out.display()))?;
    let pk = image::public_key(&seed);
    println!(
        "signed {} ({} B firmware + {} B trailer and signature) for product {product:#010x}, \
         version {}.{}.{}, public key {}",
        out.display(),
        bin.len(),
        signed.len() - bin.len(),
        version >> 16,
        (version >> 8) & 0xFF,
        version & 0xFF,
        hex(&pk)
    );
    if allow_downgrade {
        println!(
            "NOTE: --allow-downgrade: boards running a newer version accept this image (the override is signed)"
        );
    }
    if seed == image::TEST_SEED {
        println!("WARNING: signed with the TEST key (keys/test-only.sk): never ship this image");
    }
    Ok(out)
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// `cargo xtask keygen OUT`: writes `OUT.sk` and `OUT.pk`.
pub fn keygen(args: &[String]) -> Result<()> {
    let [out] = args else {
        return Err("usage: cargo xtask keygen OUT (writes OUT.sk and OUT.pk)".into());
    };
    let (sk, pk) = (format!("{out}.sk"), format!("{out}.pk"));
    for p in [&sk, &pk] {
        if Path::new(p).exists() {
            return Err(format!(
                "{p} exists: keygen never overwrites a key, pick another OUT"
            ));
        }
    }
    let mut seed = [0u8; 32];
    fs::File::open("/dev/urandom")
        .and_then(|mut f| f.read_exact(&mut seed))
        .map_err(|e| format!("cannot read /dev/urandom for the key: {e}"))?;
    write_private(Path::new(&sk), &seed)?;
    let public = image::public_key(&seed);
    fs::write(&pk, public).map_err(|e| format!("{pk}: {e}"))?;
    println!(
        "wrote {sk} (private: keep it offline, in an HSM or a CI secret, never in the repository)"
    );
    println!(
        "wrote {pk} (public {}: build it into the bootloader)",
        hex(&public)
    );
    Ok(())
}

/// Writes the private key readable by its owner only (Unix).
fn write_private(path: &Path, seed: &[u8; 32]) -> Result<()> {
    let mut o = fs::OpenOptions::new();
    o.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut o, 0o600);
    let mut f = o
        .open(path)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    std::io::Write::write_all(&mut f, seed).map_err(|e| format!("{}: {e}", path.display()))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn garbage_is_not_an_elf() {
        assert!(flash_binary(b"not an elf").is_err());
    }

    #[test]
    fn the_test_key_files_are_a_pair() {
        let root = crate::root();
        let sk = read_key(&root.join("keys/test-only.sk")).unwrap();
        let pk = read_key(&root.join("keys/test-only.pk")).unwrap();
        assert_eq!(image::public_key(&sk), pk);
        assert_eq!(sk, image::TEST_SEED);
    }

    #[test]
    fn keygen_writes_a_pair_and_never_overwrites() {
        let dir = std::env::temp_dir().join(format!("perpend-keygen-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let out = dir.join("k").display().to_string();
        keygen(std::slice::from_ref(&out)).unwrap();
        let sk = read_key(Path::new(&format!("{out}.sk"))).unwrap();
        let pk = read_key(Path::new(&format!("{out}.pk"))).unwrap();
        assert_eq!(image::public_key(&sk), pk);
        assert_ne!(sk, image::TEST_SEED);
        assert!(keygen(std::slice::from_ref(&out))
            .unwrap_err()
            .contains("exists"));
        fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_key_file_of_the_wrong_length_names_the_fix() {
        let p = std::env::temp_dir().join(format!("perpend-badkey-{}", std::process::id()));
        fs::write(&p, [1u8; 31]).unwrap();
        assert!(read_key(&p).unwrap_err().contains("cargo xtask keygen"));
        fs::remove_file(&p).unwrap();
    }
}

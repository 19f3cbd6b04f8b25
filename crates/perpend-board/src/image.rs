//! Signed firmware images: the format `cargo xtask fw --sign` writes and
//! the board checks before it lets the bootloader swap an image in.
//!
//! Layout (all integers little-endian):
//!
//! ```text
//! payload (the firmware binary, n bytes)
//! identity trailer, 48 bytes: "PPIM", product code u32, version u32
//!                             (bits 0..23 major.minor.patch, bits 24..31
//!                             flags), payload length u32, SHA-256(payload) [32]
//! signature, 64 bytes:        ed25519(secret key, SHA-512(payload ‖ trailer))
//! ```
//!
//! The signature is embassy-boot's (`FirmwareUpdater::verify_and_mark_updated`
//! with the `ed25519-salty` feature): an ed25519 signature (RFC 8032, 32-byte
//! public key, 64-byte signature) of the 64-byte SHA-512 digest of the first
//! `update_len` bytes of the DFU partition, here `update_len` = image length
//! − 64, the signature appended at the end as in embassy-boot's signing
//! example. The trailer inside the signed bytes adds what embassy-boot does
//! not check: the product code (0x1018 sub 2) so an image for another board
//! is refused, the version reported in 0x1F56, and a SHA-256 of the payload
//! (written by the signer and read for 0x1F56's hash byte; the board does
//! not recompute it: the signature already covers the payload, and the
//! SHA-256 code cost 7.4 KB of flash, issue 50 item 7).
//!
//! **Versions only go up** (issue 50 item 5, [`check_version`]): the board
//! refuses an image older than the one it runs ([`ImageError::Downgrade`]),
//! so an older signed image with a known fault cannot be put back over
//! CAN. The same version is accepted (a reinstall). The override is
//! signed: [`FLAG_ALLOW_DOWNGRADE`] in the trailer's flag byte, set by
//! `cargo xtask fw --sign KEY --allow-downgrade`, so only the holder of
//! the private key can authorise a downgrade (docs/firmware.md).
//!
//! Limits: images up to 4 GiB − 1; reads in 256-byte chunks (the buffer is
//! on the stack); one public key.

use salty::{PublicKey, Sha512, Signature};
#[cfg(any(test, feature = "std"))]
use sha2::{Digest, Sha256};

/// Bytes of the signature at the end of an image.
pub const SIGNATURE_LEN: usize = 64;
/// Bytes of the identity trailer before the signature.
pub const TRAILER_LEN: usize = 48;
/// Magic at the start of the trailer.
pub const MAGIC: [u8; 4] = *b"PPIM";
/// Trailer flag (version word bit 31): this image may replace a newer one.
pub const FLAG_ALLOW_DOWNGRADE: u8 = 1 << 7;
/// The version bits of the trailer's version word.
pub const VERSION_MASK: u32 = 0x00FF_FFFF;
/// Bytes read per step while hashing.
const CHUNK: usize = 256;

/// Why an image is refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ImageError {
    /// Shorter than trailer + signature, or the trailer's payload length
    /// does not match the image length (truncated or padded image).
    Truncated,
    /// No trailer where it belongs: a raw binary not signed by `cargo xtask
    /// fw --sign`, or an image cut short.
    Unsigned,
    /// The signature does not verify against the board's public key.
    BadSignature,
    /// The board's public key is not a valid ed25519 point.
    BadKey,
    /// The image is for another product code.
    WrongProduct,
    /// The payload's SHA-256 differs from the trailer's. No longer
    /// checked on the board (issue 50 item 7): the signature covers the
    /// payload and the trailer, so only the key holder can make the two
    /// disagree; kept for its 0x1F57 mapping and the host's tools.
    BadHash,
    /// The store could not read the image back.
    Read,
    /// The image is older than the running one and does not carry
    /// [`FLAG_ALLOW_DOWNGRADE`].
    Downgrade,
}

impl ImageError {
    /// One-byte code (EMCY manufacturer byte 2).
    pub const fn code(self) -> u8 {
        match self {
            ImageError::Truncated => 1,
            ImageError::Unsigned => 2,
            ImageError::BadSignature => 3,
            ImageError::BadKey => 4,
            ImageError::WrongProduct => 5,
            ImageError::BadHash => 6,
            ImageError::Read => 7,
            ImageError::Downgrade => 8,
        }
    }
}

/// What the board trusts: the public key built in and its product code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Trust {
    /// ed25519 public key (32 bytes, RFC 8032 encoding).
    pub public_key: [u8; 32],
    /// This board's product code (0x1018 sub 2).
    pub product: u32,
}

/// The identity trailer of a verified image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Identity {
    /// Product code the image is for.
    pub product: u32,
    /// Version, `major << 16 | minor << 8 | patch`.
    pub version: u32,
    /// Flags (`FLAG_*`), the top byte of the trailer's version word.
    pub flags: u8,
    /// Payload length \[bytes\].
    pub payload_len: u32,
    /// SHA-256 of the payload.
    pub sha256: [u8; 32],
}

impl Identity {
    /// 0x1F56: the first byte of the SHA-256 in bits 24..31, the version
    /// (`major.minor.patch`, one byte each) in bits 0..23.
    pub fn identification(&self) -> u32 {
        (u32::from(self.sha256[0]) << 24) | (self.version & 0x00FF_FFFF)
    }

    /// The trailer bytes.
    pub fn to_bytes(&self) -> [u8; TRAILER_LEN] {
        let mut t = [0u8; TRAILER_LEN];
        t[..4].copy_from_slice(&MAGIC);
        t[4..8].copy_from_slice(&self.product.to_le_bytes());
        let v = (self.version & VERSION_MASK) | (u32::from(self.flags) << 24);
        t[8..12].copy_from_slice(&v.to_le_bytes());
        t[12..16].copy_from_slice(&self.payload_len.to_le_bytes());
        t[16..].copy_from_slice(&self.sha256);
        t
    }

    /// Parses a trailer.
    ///
    /// # Errors
    /// [`ImageError::Unsigned`] without the magic.
    pub fn from_bytes(t: &[u8; TRAILER_LEN]) -> Result<Self, ImageError> {
        if t[..4] != MAGIC {
            return Err(ImageError::Unsigned);
        }
        let word = |i: usize| u32::from_le_bytes([t[i], t[i + 1], t[i + 2], t[i + 3]]);
        let mut sha256 = [0u8; 32];
        sha256.copy_from_slice(&t[16..]);
        Ok(Self {
            product: word(4),
            version: word(8) & VERSION_MASK,
            flags: (word(8) >> 24) as u8,
            payload_len: word(12),
            sha256,
        })
    }
}

/// Whether an image `new` may replace the running version `running`
/// (both `major.minor.patch` words; see the module docs).
///
/// # Errors
/// [`ImageError::Downgrade`] for an older image without
/// [`FLAG_ALLOW_DOWNGRADE`].
pub fn check_version(new: &Identity, running: u32) -> Result<(), ImageError> {
    let downgrade = new.version & VERSION_MASK < running & VERSION_MASK;
    if downgrade && new.flags & FLAG_ALLOW_DOWNGRADE == 0 {
        return Err(ImageError::Downgrade);
    }
    Ok(())
}

/// `major.minor.patch` as an [`Identity::version`] (each part saturated
/// to one byte).
pub fn version(major: u32, minor: u32, patch: u32) -> u32 {
    (major.min(255) << 16) | (minor.min(255) << 8) | patch.min(255)
}

/// Verifies the image of `len` bytes that `read(offset, buf)` reads back
/// (the DFU partition): trailer, signature, product (the trailer's SHA-256
/// is not recomputed: the signature covers the payload).
///
/// # Errors
/// The first reason the image is refused.
pub fn verify<R>(mut read: R, len: u32, trust: &Trust) -> Result<Identity, ImageError>
where
    R: FnMut(u32, &mut [u8]) -> Result<(), ImageError>,
{
    let tail = (TRAILER_LEN + SIGNATURE_LEN) as u32;
    if len < tail {
        return Err(ImageError::Truncated);
    }
    let signed_len = len - SIGNATURE_LEN as u32;
    let mut trailer = [0u8; TRAILER_LEN];
    read(signed_len - TRAILER_LEN as u32, &mut trailer)?;
    let id = Identity::from_bytes(&trailer)?;
    if id.payload_len != len - tail {
        return Err(ImageError::Truncated);
    }
    let mut sig = [0u8; SIGNATURE_LEN];
    read(signed_len, &mut sig)?;
    let key = PublicKey::try_from(&trust.public_key).map_err(|_| ImageError::BadKey)?;
    let sha512 = digest(&mut read, signed_len)?;
    key.verify(&sha512, &Signature::from(&sig))
        .map_err(|_| ImageError::BadSignature)?;
    if id.product != trust.product {
        return Err(ImageError::WrongProduct);
    }
    Ok(id)
}

/// SHA-512 of bytes `0..signed_len`.
fn digest<R>(read: &mut R, signed_len: u32) -> Result<[u8; 64], ImageError>
where
    R: FnMut(u32, &mut [u8]) -> Result<(), ImageError>,
{
    let mut sha512 = Sha512::new();
    let mut buf = [0u8; CHUNK];
    let mut at = 0u32;
    while at < signed_len {
        let n = (signed_len - at).min(CHUNK as u32) as usize;
        read(at, &mut buf[..n])?;
        sha512.update(&buf[..n]);
        at += n as u32;
    }
    Ok(sha512.finalize())
}

/// The public key of an ed25519 secret seed.
pub fn public_key(seed: &[u8; 32]) -> [u8; 32] {
    salty::Keypair::from(seed).public.to_bytes()
}

/// A signed image of `payload` (host only: `cargo xtask fw --sign`, tests).
#[cfg(any(test, feature = "std"))]
pub fn sign(payload: &[u8], product: u32, version: u32, seed: &[u8; 32]) -> std::vec::Vec<u8> {
    sign_with_flags(payload, product, version, 0, seed)
}

/// [`sign`] with trailer flags (`FLAG_*`).
#[cfg(any(test, feature = "std"))]
pub fn sign_with_flags(
    payload: &[u8],
    product: u32,
    version: u32,
    flags: u8,
    seed: &[u8; 32],
) -> std::vec::Vec<u8> {
    let id = Identity {
        product,
        version: version & VERSION_MASK,
        flags,
        payload_len: payload.len().min(u32::MAX as usize) as u32,
        sha256: Sha256::digest(payload).into(),
    };
    let mut out = payload.to_vec();
    out.extend_from_slice(&id.to_bytes());
    let digest = Sha512::new().updated(&out).finalize();
    let sig = salty::Keypair::from(seed).sign(&digest);
    out.extend_from_slice(&sig.to_bytes());
    out
}

/// The test key pair's seed (keys/test-only.sk): NEVER for a shipped
/// board, anyone can sign with it.
pub const TEST_SEED: [u8; 32] = *include_bytes!("../../../keys/test-only.sk");

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    const PRODUCT: u32 = 0x5045_5250;

    fn trust() -> Trust {
        Trust {
            public_key: public_key(&TEST_SEED),
            product: PRODUCT,
        }
    }

    fn check(img: &[u8]) -> Result<Identity, ImageError> {
        let read = |o: u32, b: &mut [u8]| {
            let o = o as usize;
            let src = img.get(o..o + b.len()).ok_or(ImageError::Read)?;
            b.copy_from_slice(src);
            Ok(())
        };
        verify(read, img.len() as u32, &trust())
    }

    fn payload(n: usize) -> Vec<u8> {
        (0..n).map(|i| (i * 31 + 7) as u8).collect()
    }

    #[test]
    fn a_signed_image_verifies_for_every_length_around_the_chunk() {
        for n in [0, 1, 255, 256, 257, 1000, 4096] {
            let img = sign(&payload(n), PRODUCT, version(1, 2, 3), &TEST_SEED);
            let id = check(&img).unwrap();
            assert_eq!(id.payload_len as usize, n);
            assert_eq!(id.version, 0x01_02_03);
            assert_eq!(id.sha256, <[u8; 32]>::from(Sha256::digest(payload(n))));
            assert_eq!(id.identification() >> 24, u32::from(id.sha256[0]));
        }
    }

    #[test]
    fn the_signature_is_embassy_boots_over_the_sha512_of_the_signed_bytes() {
        let img = sign(&payload(600), PRODUCT, 1, &TEST_SEED);
        let (signed, sig) = img.split_at(img.len() - SIGNATURE_LEN);
        let digest = Sha512::new().updated(signed).finalize();
        let key = PublicKey::try_from(&public_key(&TEST_SEED)).unwrap();
        let sig: [u8; 64] = sig.try_into().unwrap();
        assert!(key.verify(&digest, &Signature::from(&sig)).is_ok());
        // Not over the raw bytes.
        assert!(key.verify(signed, &Signature::from(&sig)).is_err());
    }

    #[test]
    fn every_damaged_image_is_refused_with_its_reason() {
        let good = sign(&payload(700), PRODUCT, 5, &TEST_SEED);
        let mut flipped = good.clone();
        flipped[100] ^= 1;
        assert_eq!(check(&flipped), Err(ImageError::BadSignature));
        let mut bad_sig = good.clone();
        let last = bad_sig.len() - 1;
        bad_sig[last] ^= 0x40;
        assert_eq!(check(&bad_sig), Err(ImageError::BadSignature));
        assert_eq!(check(&good[..good.len() - 1]), Err(ImageError::Unsigned));
        assert_eq!(check(&good[..50]), Err(ImageError::Truncated));
        assert_eq!(check(&payload(700)), Err(ImageError::Unsigned));
        let other = sign(&payload(700), PRODUCT + 1, 5, &TEST_SEED);
        assert_eq!(check(&other), Err(ImageError::WrongProduct));
        let stranger = sign(&payload(700), PRODUCT, 5, &[9u8; 32]);
        assert_eq!(check(&stranger), Err(ImageError::BadSignature));
        assert!(check(&good).is_ok(), "the original still verifies");
    }

    #[test]
    fn versions_only_go_up_unless_the_signed_flag_allows() {
        let v = |ver, flags| {
            let img = sign_with_flags(&payload(10), PRODUCT, ver, flags, &TEST_SEED);
            check(&img).unwrap()
        };
        let running = version(1, 2, 0);
        assert_eq!(check_version(&v(version(1, 3, 0), 0), running), Ok(()));
        assert_eq!(
            check_version(&v(version(1, 2, 0), 0), running),
            Ok(()),
            "reinstall"
        );
        assert_eq!(
            check_version(&v(version(1, 1, 9), 0), running),
            Err(ImageError::Downgrade)
        );
        let allowed = v(version(1, 1, 9), FLAG_ALLOW_DOWNGRADE);
        assert_eq!(
            allowed.version,
            version(1, 1, 9),
            "the flag is not the version"
        );
        assert_eq!(check_version(&allowed, running), Ok(()));
        // 0x1F56's hash byte of the running image does not count
        assert_eq!(check_version(&v(version(1, 2, 0), 0), 0xFF01_0200), Ok(()));
    }

    #[test]
    fn a_trailer_with_the_wrong_length_is_truncated() {
        let mut img = sign(&payload(300), PRODUCT, 5, &TEST_SEED);
        // Drop one payload byte: the trailer's length no longer matches.
        img.remove(0);
        assert_eq!(check(&img), Err(ImageError::Truncated));
    }
}

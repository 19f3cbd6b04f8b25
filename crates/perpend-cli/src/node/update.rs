//! `perpend node update FILE`: a signed image (`cargo xtask fw --sign`)
//! onto a board over CANopen, CiA 302-3 program download.
//!
//! Steps, each stopping at its first failure with the cause: the file is a
//! signed image (`perpend_board::image` trailer) for this board's product
//! code (0x1018 sub 2); the board is pre-operational (heartbeat); 0x1F56
//! (the active image) is read; the image goes to 0x1F50 sub 1 by SDO block
//! download with CRC (progress on stderr); the board verifies the signature
//! itself when the last byte arrives (a refusal: 0x1F57 in words); 0x1F51
//! sub 1 = 1 (start) lets the bootloader swap it in at the restart; the
//! boot-up message is awaited, and 0x1F56 read again must be the new
//! image's, otherwise the board has rolled back (the new image did not
//! confirm itself). Old and new version are printed.
//!
//! Every attempt that reached the board leaves an update record
//! (`update_record.rs`, `perpend.update/1`): `--record FILE`, by default
//! `update-SERIAL-TIME.json` in the current directory.
//!
//! Nothing here can brick the board: until "start" only the DFU partition
//! is written, and an image that does not come up is rolled back by the
//! bootloader. Limits: one program (0x1F50 sub 1); no resume of an
//! interrupted download (it starts again from byte 0).

use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use perpend_board::image::{Identity, SIGNATURE_LEN, TRAILER_LEN};
use perpend_board::program::{FLASH_BAD_SIGNATURE, FLASH_DOWNGRADE, FLASH_WRONG_PRODUCT};
use perpend_can::od;

pub use super::update_record::version_words;
use super::update_record::{Board, UpdateRecord};
use super::Node;
use crate::canopen::NodeState;

/// How long the board may take for the last answer of the download (it
/// verifies the signature then).
const VERIFY_TIMEOUT: Duration = Duration::from_secs(5);
/// How long the board may take to restart after "start": the bootloader's
/// swap of 110 pages takes about 10 s on the G474 (docs/firmware.md), a
/// rollback as long again; 30 s leaves room for both.
const RESTART_TIMEOUT: Duration = Duration::from_secs(30);

/// Arguments of `perpend node update`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The signed image (`cargo xtask fw --sign KEY` writes
    /// `target/thumbv7em-none-eabihf/release/perpend-fw.signed.bin`).
    pub file: PathBuf,
    /// Where to write the update record (`perpend.update/1`); default
    /// `update-SERIAL-TIME.json` in the current directory. Never
    /// overwritten.
    #[arg(long, value_name = "FILE")]
    pub record: Option<PathBuf>,
}

/// 0x1F57 in words.
pub fn flash_words(status: u32) -> &'static str {
    match status {
        od::FLASH_OK => "image verified",
        od::FLASH_BUSY => "download in progress",
        od::FLASH_NO_PROGRAM => "no valid program downloaded",
        od::FLASH_FORMAT_UNKNOWN => "not a signed image, or cut short (no trailer)",
        od::FLASH_FORMAT_ERROR => "image truncated or corrupted (length or hash)",
        od::FLASH_WRITE_ERROR => "writing the update partition failed",
        od::FLASH_ADDRESS_ERROR => "the image is larger than the update partition",
        od::FLASH_SECURED => "the board takes no download now",
        FLASH_WRONG_PRODUCT => "the image is for another product",
        FLASH_BAD_SIGNATURE => {
            "the signature does not verify against the board's key: the image was signed \
             with another key, or its signature was changed after signing"
        }
        FLASH_DOWNGRADE => {
            "the image is older than the one the board runs (versions only go up; \
             sign it with `cargo xtask fw --sign KEY --allow-downgrade` to allow it)"
        }
        _ => "unknown flash status",
    }
}

/// The identity trailer of a signed image file.
fn file_identity(img: &[u8], file: &str) -> Result<Identity> {
    let end = img.len().saturating_sub(SIGNATURE_LEN);
    let t = img
        .get(end.saturating_sub(TRAILER_LEN)..end)
        .and_then(|t| <&[u8; TRAILER_LEN]>::try_from(t).ok());
    match t.map(Identity::from_bytes) {
        Some(Ok(id)) if id.payload_len as usize + TRAILER_LEN + SIGNATURE_LEN == img.len() => {
            Ok(id)
        }
        _ => bail!(
            "{file} is not a signed image (no identity trailer, or cut short): sign the \
             firmware with `cargo xtask fw --sign KEY` and pass the .signed.bin it writes"
        ),
    }
}

/// The file's payload against the SHA-256 its signed trailer carries: a
/// byte changed after signing (on disk, in a copy) is named before
/// anything is sent, rather than as a signature the board refuses.
fn file_intact(img: &[u8], id: &Identity, file: &str) -> Result<()> {
    use sha2::Digest;
    let payload = img.get(..id.payload_len as usize).unwrap_or_default();
    if sha2::Sha256::digest(payload).as_slice() != id.sha256 {
        bail!(
            "{file} was changed after it was signed: its payload's SHA-256 differs from the \
             one its signed trailer carries (a changed byte, on disk or in a copy). Nothing was \
             written; take the file `cargo xtask fw --sign` wrote, or sign again"
        );
    }
    Ok(())
}

/// The checks of the file alone (readable, signed, unchanged since
/// signing), so that a wrong file is named before the bus is opened.
///
/// # Errors
/// The file's first problem, in a sentence.
pub fn check_file(path: &std::path::Path) -> Result<()> {
    let file = path.display().to_string();
    let img = std::fs::read(path).with_context(|| format!("cannot read {file}"))?;
    let id = file_identity(&img, &file)?;
    file_intact(&img, &id, &file)
}

/// Checks the board is pre-operational (by its heartbeat).
fn check_preop(node: &mut Node) -> Result<()> {
    let hb = node.heartbeat_ms()?;
    if let Some(s @ (NodeState::Operational | NodeState::Stopped)) = node.state(hb)? {
        bail!(
            "{} is {s}: a firmware update needs it pre-operational (the robot controller may be \
             using it). Nothing was written; switch it with `perpend node … nmt preop` when \
             the machine allows",
            node.name()
        );
    }
    Ok(())
}

/// Progress on stderr: a rewritten line on a terminal, a line per 10 %
/// otherwise.
fn progress(total: usize) -> impl FnMut(usize) {
    let tty = std::io::stderr().is_terminal();
    let mut last = usize::MAX;
    move |n| {
        let pct = n * 100 / total.max(1);
        if tty {
            eprint!("\rdownloading: {n}/{total} B ({pct} %)");
        } else if pct / 10 != last {
            eprintln!("downloading: {n}/{total} B ({pct} %)");
        }
        last = pct / 10;
    }
}

/// The download's failure in words, with 0x1F57 when the board answers
/// (then a refusal in `rec`).
fn download_failed(
    node: &mut Node,
    e: crate::canopen::ClientError,
    rec: &mut UpdateRecord,
) -> anyhow::Error {
    let status = node.client.read_u32(node.id, 0x1F57, 1).ok();
    let name = node.name();
    match status {
        Some(s) if s != od::FLASH_BUSY && s != od::FLASH_OK => {
            rec.fails_as("refused");
            anyhow::anyhow!(
                "{name} refused the image: {} (0x1F57 = {s:#x}). It keeps running its present \
             image",
                flash_words(s)
            )
        }
        _ => anyhow::anyhow!(
            "the download to {name} failed: {e}. The board keeps running its present image; \
             run the update again"
        ),
    }
}

/// `perpend node update FILE`.
///
/// # Errors
/// The first cause of a failure, in a sentence; the board keeps running
/// its image. A record that cannot be written is an error too (after the
/// update's own outcome is printed).
pub fn run(node: &mut Node, a: &Args) -> Result<()> {
    let file = a.file.display().to_string();
    let img = std::fs::read(&a.file).with_context(|| format!("cannot read {file}"))?;
    let want = file_identity(&img, &file)?;
    file_intact(&img, &want, &file)?;
    node.hello()?;
    let id = node.id;
    let product = node.client.read_u32(id, 0x1018, 2)?;
    let board = Board {
        bus: node.client.bus_name().to_string(),
        node_id: id,
        serial: format!("{:#010x}", node.client.read_u32(id, 0x1018, 4)?),
        product: format!("{product:#010x}"),
        firmware_before: node.client.read_string(id, 0x100A, 0)?,
    };
    let mut rec = UpdateRecord::begin(board, &a.file, &img, &want);
    let r = update(node, &img, &want, product, &mut rec);
    let flash = node.client.read_u32(id, 0x1F57, 1).ok();
    rec.finish(&r, flash);
    let path = a.record.clone().unwrap_or_else(|| rec.default_name());
    match (rec.write(&path), r) {
        (Ok(()), r) => {
            eprintln!("update record: {}", path.display());
            r
        }
        (Err(w), Ok(())) => Err(w.context(format!(
            "{}: updated, but the record was not written",
            node.name()
        ))),
        (Err(w), Err(e)) => {
            eprintln!("perpend node update: the record was not written either: {w:#}");
            Err(e)
        }
    }
}

/// The steps after the board is identified, each noted in `rec`.
fn update(
    node: &mut Node,
    img: &[u8],
    want: &Identity,
    product: u32,
    rec: &mut UpdateRecord,
) -> Result<()> {
    let file = rec.image.path.clone();
    rec.fails_as("refused");
    check_preop(node)?;
    let id = node.id;
    if want.product != product {
        bail!(
            "{file} is for product {:#010x}, {} is product {product:#010x}: nothing was written",
            want.product,
            node.name()
        );
    }
    let old = node.client.read_u32(id, 0x1F56, 1)?;
    rec.before(old);
    rec.step(format!("pre-operational, running {}", version_words(old)));
    eprintln!("{}: running {}", node.name(), version_words(old));
    let data = (0x1F50, 1);
    rec.fails_as("failed");
    let r = node
        .client
        .download_block(id, data, img, VERIFY_TIMEOUT, &mut progress(img.len()));
    if std::io::stderr().is_terminal() {
        eprintln!();
    }
    let resent = r.map_err(|e| download_failed(node, e, rec))?;
    if resent > 0 {
        eprintln!(
            "{}: {resent} segments lost on the bus were resent",
            node.name()
        );
    }
    rec.step(format!(
        "{} B downloaded to 0x1F50 sub 1, verified by the board ({resent} segments resent)",
        img.len()
    ));
    start_and_check(node, old, want.identification(), rec)
}

/// 0x1F51 start, the restart, and the check of 0x1F56 after it.
fn start_and_check(node: &mut Node, old: u32, new: u32, rec: &mut UpdateRecord) -> Result<()> {
    let id = node.id;
    if let Err(e) = node.client.download(id, 0x1F51, 1, &[od::PROGRAM_START]) {
        return Err(download_failed(node, e, rec));
    }
    rec.step("0x1F51 sub 1 = start");
    let ticker = crate::progress::Ticker::start("restarting (the bootloader swaps the images)");
    let booted = node.client.wait_bootup(id, RESTART_TIMEOUT);
    drop(ticker);
    booted.map_err(|e| anyhow::anyhow!("{e}: the board did not restart after \"start\""))?;
    rec.step("boot-up received");
    let now = node.client.read_u32(id, 0x1F56, 1)?;
    rec.after(now);
    if now == new {
        println!(
            "{}: updated from {} to {}",
            node.name(),
            version_words(old),
            version_words(now)
        );
        return Ok(());
    }
    if now == old {
        rec.fails_as("rolled back");
        bail!(
            "{}: the new image {} did not confirm itself and the bootloader rolled back: it \
             runs {} again. Check the new firmware (it must come up completely and mark \
             itself booted)",
            node.name(),
            version_words(new),
            version_words(old)
        );
    }
    bail!(
        "{}: after the restart it runs {}, neither the old {} nor the new {}",
        node.name(),
        version_words(now),
        version_words(old),
        version_words(new)
    )
}

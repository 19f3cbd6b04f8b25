//! The update record (`perpend.update/1`): the file `perpend node update`
//! leaves for every attempt that reached a board, successful or not, so a
//! quality engineer can file what was put on which board, by whom's build,
//! and how it ended. Schema in `docs/record.md` ("Firmware update record").
//!
//! Contents: when (start and end, UTC), the tool's version, the bus and
//! node-id, the board (serial 0x1018 sub 4, product 0x1018 sub 2, firmware
//! name 0x100A before), the image file (path, size, SHA-256 of the file,
//! the trailer's version, product and payload SHA-256), the active image
//! (0x1F56) before and after, the outcome (`updated`, `refused`,
//! `rolled back`, `failed`) with its first cause and the flash status
//! (0x1F57) when the board gave one, and the steps with their times.
//!
//! Limits: written after the command ends, not as it goes (a killed client
//! leaves no record; the board then still runs its old image, see
//! `update.rs`); the default file name carries the serial and the start
//! time to the second, so two updates of one board in one second would
//! share a name (the second refuses to overwrite).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use perpend_board::image::Identity;
use perpend_calib::record::{sha256_hex, tool_version, utc_now};
use serde::Serialize;

/// `major.minor.patch (#xx)` of a 0x1F56 identification.
pub fn version_words(ident: u32) -> String {
    if ident == 0 {
        return "none (0x1F56 = 0)".into();
    }
    let v = ident & 0x00FF_FFFF;
    format!(
        "{}.{}.{} (image {:02x})",
        v >> 16,
        (v >> 8) & 0xFF,
        v & 0xFF,
        ident >> 24
    )
}

/// Value of the `schema` field.
pub const SCHEMA: &str = "perpend.update/1";

/// The board as found before the update.
#[derive(Serialize, Debug, Clone)]
pub struct Board {
    /// `--bus`, as given.
    pub bus: String,
    /// Node-id.
    pub node_id: u8,
    /// 0x1018 sub 4, hex.
    pub serial: String,
    /// 0x1018 sub 2, hex.
    pub product: String,
    /// 0x100A before the update.
    pub firmware_before: String,
}

/// The image file.
#[derive(Serialize, Debug, Clone)]
pub struct ImageFile {
    /// Path as given.
    pub path: String,
    /// Size [bytes].
    pub bytes: usize,
    /// SHA-256 of the whole file (payload, trailer, signature).
    pub sha256: String,
    /// Version from the trailer, `major.minor.patch`.
    pub version: String,
    /// Product code from the trailer, hex.
    pub product: String,
    /// SHA-256 of the payload, from the trailer.
    pub payload_sha256: String,
}

/// One step and when it ended.
#[derive(Serialize, Debug, Clone)]
pub struct Step {
    /// UTC, to the second.
    pub time_utc: String,
    /// What happened.
    pub what: String,
}

/// The record.
#[derive(Serialize, Debug, Clone)]
pub struct UpdateRecord {
    /// [`SCHEMA`].
    pub schema: &'static str,
    /// When the command started.
    pub started_utc: String,
    /// When it ended.
    pub finished_utc: String,
    /// The tool that ran it.
    pub tool: String,
    /// The board.
    pub board: Board,
    /// The image.
    pub image: ImageFile,
    /// 0x1F56 before, in words (`none` before it was read).
    pub active_before: String,
    /// 0x1F56 after the restart, in words; `not read` when the command
    /// ended before.
    pub active_after: String,
    /// `updated`, `refused`, `rolled back` or `failed`.
    pub outcome: String,
    /// The first cause when not `updated`.
    pub cause: Option<String>,
    /// 0x1F57 at the end, when the board answered it.
    pub flash_status: Option<u32>,
    /// The steps, in order.
    pub steps: Vec<Step>,
}

impl UpdateRecord {
    /// A record of putting `img` (read from `path`, trailer `id`) on `board`.
    pub fn begin(board: Board, path: &Path, img: &[u8], id: &Identity) -> Self {
        let v = id.version;
        Self {
            schema: SCHEMA,
            started_utc: utc_now(),
            finished_utc: String::new(),
            tool: tool_version(),
            board,
            image: ImageFile {
                path: path.display().to_string(),
                bytes: img.len(),
                sha256: sha256_hex(img),
                version: format!("{}.{}.{}", v >> 16, (v >> 8) & 0xFF, v & 0xFF),
                product: format!("{:#010x}", id.product),
                payload_sha256: id.sha256.iter().map(|b| format!("{b:02x}")).collect(),
            },
            active_before: "none".into(),
            active_after: "not read".into(),
            outcome: "failed".into(),
            cause: None,
            flash_status: None,
            steps: Vec::new(),
        }
    }

    /// Appends a step, timed now.
    pub fn step(&mut self, what: impl Into<String>) {
        self.steps.push(Step {
            time_utc: utc_now(),
            what: what.into(),
        });
    }

    /// Sets 0x1F56 before the download.
    pub fn before(&mut self, ident: u32) {
        self.active_before = version_words(ident);
    }

    /// Sets 0x1F56 after the restart.
    pub fn after(&mut self, ident: u32) {
        self.active_after = version_words(ident);
    }

    /// Names the outcome should the command fail from here on
    /// (`refused`, `rolled back`; `failed` until set).
    pub fn fails_as(&mut self, outcome: &str) {
        self.outcome = outcome.into();
    }

    /// Closes the record with the command's result and the last flash
    /// status read.
    pub fn finish(&mut self, r: &Result<()>, flash: Option<u32>) {
        self.finished_utc = utc_now();
        self.flash_status = flash;
        match r {
            Ok(()) => self.outcome = "updated".into(),
            Err(e) => self.cause = Some(format!("{e:#}")),
        }
    }

    /// The default file name: `update-SERIAL-YYYYMMDDTHHMMSSZ.json`.
    pub fn default_name(&self) -> PathBuf {
        let serial = self.board.serial.trim_start_matches("0x");
        let t: String = self
            .started_utc
            .chars()
            .filter(|c| c.is_ascii_alphanumeric())
            .collect();
        PathBuf::from(format!("update-{serial}-{t}.json"))
    }

    /// Writes the record to `path` (never over an existing file).
    ///
    /// # Errors
    /// The file exists or cannot be written.
    pub fn write(&self, path: &Path) -> Result<()> {
        if path.exists() {
            bail!(
                "{} exists: an update record is never overwritten; pass another --record",
                path.display()
            );
        }
        let text = serde_json::to_string_pretty(self)?;
        std::fs::write(path, text + "\n")
            .with_context(|| format!("cannot write the update record {}", path.display()))
    }
}

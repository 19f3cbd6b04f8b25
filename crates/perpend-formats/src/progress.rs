//! Progress on stderr for work that takes longer than about two seconds
//! (benches, many re-simulations, the study).
//!
//! The bar goes to stderr only, so `--json` output on stdout stays clean;
//! it is drawn only when stderr is a terminal (indicatif's rule), so logs
//! and CI get nothing; `perpend --quiet` turns it off everywhere.

use std::sync::atomic::{AtomicBool, Ordering};

use indicatif::{ProgressBar, ProgressStyle};

static QUIET: AtomicBool = AtomicBool::new(false);

/// Turns every progress bar off (`perpend --quiet`).
pub fn set_quiet(quiet: bool) {
    QUIET.store(quiet, Ordering::Relaxed);
}

/// Whether every progress output is off (`perpend --quiet`).
pub fn quiet() -> bool {
    QUIET.load(Ordering::Relaxed)
}

/// A bar counting `len` units of work, or nothing when quiet.
#[derive(Debug)]
pub struct Progress(Option<ProgressBar>);

impl Progress {
    /// Starts a bar labelled `what`.
    pub fn new(len: u64, what: &str) -> Self {
        if QUIET.load(Ordering::Relaxed) {
            return Self(None);
        }
        let bar = ProgressBar::new(len);
        let style = ProgressStyle::with_template(
            "{msg:>24} [{bar:32}] {pos}/{len} ({elapsed}, about {eta} left)",
        )
        .map(|s| s.progress_chars("=> "))
        .unwrap_or_else(|_| ProgressStyle::default_bar());
        bar.set_style(style);
        bar.set_message(what.to_string());
        Self(Some(bar))
    }

    /// One more unit done.
    pub fn inc(&self) {
        if let Some(b) = &self.0 {
            b.inc(1);
        }
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        if let Some(b) = &self.0 {
            b.finish_and_clear();
        }
    }
}

//! A progress line on stderr for the bus steps that take more than a
//! second without output of their own (an LSS scan, the restart after a
//! firmware update): one line rewritten five times a second with the
//! step, the time it has taken and a note the step updates ("2 found").
//!
//! Drawn only when stderr is a terminal and `--quiet` is not given
//! ([`shown`]), so pipes, logs and tests get nothing; cleared when the
//! step ends (the [`Ticker`] is dropped). Counted work with a known end
//! uses `perpend_formats::progress::Progress` (a bar) instead.

use std::io::{IsTerminal, Write};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Whether a progress line is drawn: on a terminal, unless quiet.
pub fn shown(quiet: bool, stderr_is_terminal: bool) -> bool {
    !quiet && stderr_is_terminal
}

/// The line: `what: 3.2 s, note`.
pub fn line(what: &str, elapsed: Duration, note: &str) -> String {
    let t = elapsed.as_secs_f64();
    if note.is_empty() {
        format!("{what}: {t:.1} s")
    } else {
        format!("{what}: {t:.1} s, {note}")
    }
}

/// A running progress line (nothing when not [`shown`]).
#[derive(Debug)]
pub struct Ticker {
    stop: Arc<AtomicBool>,
    note: Arc<Mutex<String>>,
    thread: Option<JoinHandle<()>>,
}

impl Ticker {
    /// Starts the line for the step `what`.
    pub fn start(what: &str) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let note = Arc::new(Mutex::new(String::new()));
        let on = shown(
            perpend_formats::progress::quiet(),
            std::io::stderr().is_terminal(),
        );
        let thread = on.then(|| {
            let (stop, note, what) = (stop.clone(), note.clone(), what.to_string());
            std::thread::spawn(move || draw(&what, &stop, &note))
        });
        Self { stop, note, thread }
    }

    /// Replaces the note after the time.
    pub fn note(&self, text: impl Into<String>) {
        if let Ok(mut n) = self.note.lock() {
            *n = text.into();
        }
    }
}

/// The drawing loop of one line, until `stop`; clears it at the end.
fn draw(what: &str, stop: &AtomicBool, note: &Mutex<String>) {
    let t0 = Instant::now();
    while !stop.load(Ordering::Relaxed) {
        let n = note.lock().map(|n| n.clone()).unwrap_or_default();
        let mut e = std::io::stderr().lock();
        let _ = write!(e, "\r\x1b[2K{}", line(what, t0.elapsed(), &n));
        let _ = e.flush();
        drop(e);
        std::thread::sleep(Duration::from_millis(200));
    }
    let _ = write!(std::io::stderr().lock(), "\r\x1b[2K");
}

impl Drop for Ticker {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_line_is_drawn_on_a_terminal_unless_quiet() {
        assert!(shown(false, true));
        assert!(!shown(true, true), "--quiet");
        assert!(!shown(false, false), "a pipe or a log");
    }

    #[test]
    fn the_line_says_step_time_and_note() {
        let d = Duration::from_millis(3240);
        assert_eq!(line("lss scan", d, ""), "lss scan: 3.2 s");
        assert_eq!(line("lss scan", d, "2 found"), "lss scan: 3.2 s, 2 found");
    }

    #[test]
    fn a_ticker_off_a_terminal_draws_nothing_and_ends() {
        // the test's stderr is captured, not a terminal: no thread
        let t = Ticker::start("x");
        assert!(t.thread.is_none() || std::io::stderr().is_terminal());
        t.note("1 found");
    }
}

//! A closed standard output (`perpend eds | head -1`, a pager quit early)
//! ends `perpend` quietly, as it ends a program that keeps the default
//! SIGPIPE action, instead of a panic.
//!
//! Rust ignores SIGPIPE, so a write to a closed pipe fails with
//! `BrokenPipe` and `println!` panics ("failed printing to stdout"). The
//! signal is not restored (a TCP or serial write of `perpend node` and
//! `perpend board` would then kill the process instead of returning an
//! error that names the bus); instead the panic hook and the error path of
//! `main` recognise the broken pipe and exit with [`EXIT_BROKEN_PIPE`],
//! the status a shell shows for a program killed by SIGPIPE (128 + 13),
//! printing nothing.

use std::io::ErrorKind;

/// Exit status after a closed standard output: 128 + SIGPIPE (13).
pub const EXIT_BROKEN_PIPE: u8 = 141;

/// Whether a panic message is `println!`'s on a closed standard output.
pub fn is_broken_stdout(msg: &str) -> bool {
    msg.starts_with("failed printing to stdout") && msg.contains("Broken pipe")
}

/// Whether an error was caused by writing to a closed pipe.
pub fn is_broken_pipe(e: &anyhow::Error) -> bool {
    e.chain().any(|c| {
        c.downcast_ref::<std::io::Error>()
            .is_some_and(|io| io.kind() == ErrorKind::BrokenPipe)
    })
}

/// Installs the panic hook that exits quietly on a closed standard output
/// and keeps the default report for every other panic.
pub fn install() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        let p = info.payload();
        let msg = p
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| p.downcast_ref::<&str>().copied())
            .unwrap_or("");
        if is_broken_stdout(msg) {
            std::process::exit(i32::from(EXIT_BROKEN_PIPE));
        }
        default(info);
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_broken_pipe_is_recognised_and_nothing_else() {
        assert!(is_broken_stdout(
            "failed printing to stdout: Broken pipe (os error 32)"
        ));
        assert!(!is_broken_stdout(
            "failed printing to stdout: No space left"
        ));
        assert!(!is_broken_stdout("index out of bounds"));
        let e = anyhow::Error::new(std::io::Error::from(ErrorKind::BrokenPipe)).context("writing");
        assert!(is_broken_pipe(&e));
        assert!(!is_broken_pipe(&anyhow::anyhow!("Broken pipe")));
    }
}

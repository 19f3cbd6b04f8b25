//! Firmware tasks: `cargo xtask fw`, `cargo xtask size`,
//! `cargo xtask mcu-bench [--json]`.
//!
//! * `fw` — builds the release images of the application
//!   (`cargo build --release --target thumbv7em-none-eabihf -p perpend-fw`)
//!   and of the bootloader (`-p perpend-boot`, a second cargo run so that
//!   the two do not unify their embassy-stm32 features); `fw --sign KEY`
//!   also writes the signed image (`sign.rs`).
//! * `size` — builds it (unless `--no-build`), reads the ELF's program
//!   headers and prints the flash use (the file size of every loadable
//!   segment whose load address is in flash: vector table, code, read-only
//!   data, the initial values of `.data`) and the static RAM use (the
//!   memory size of every loadable segment whose run address is in RAM:
//!   `.data`, `.bss`, `.uninit`; the stack is what remains). Fails above
//!   [`FLASH_BUDGET`] / [`RAM_BUDGET`]. Also prints the stack room: the
//!   stack (flip-link puts it at the bottom of RAM, `_stack_end` ..
//!   `_stack_start`) less the 8 KiB MPU guard (`src/board.rs`), the worst
//!   stack depth by static analysis of the call graph ([`stack`], from
//!   `llvm-objdump`) against it (fails above it), and where the run-time
//!   high-water mark is read (painted stack, object 0x200B sub 3). Then
//!   the bootloader's flash and static RAM against [`BOOT_FLASH_BUDGET`]
//!   (its region in `boot/memory.x`).
//! * `mcu-bench` — builds `xtask/mcu-bench` (its own workspace) for
//!   thumbv7em-none-eabihf, runs it on QEMU `mps2-an386` (Cortex-M4F) with
//!   one instruction per translation block and `-d exec,nochain`, and
//!   counts the instructions executed between the program's `bench_mark`
//!   calls. Installs `qemu-system-arm` from Debian when it is missing.
//!   Prints a table, or JSON with `--json` (`pipeline_insns`,
//!   `pipeline_sphere_insns`, `pipeline_sphere_steep_insns`,
//!   `pipeline_table_insns` (plane pipeline with an active linearity table
//!   on every sensor), `app_update_insns`, `app_sync_insns`,
//!   `app_update_table_insns`, `app_sync_table_insns` (the same two with
//!   an active linearity table on every sensor, written over CAN),
//!   `app_update_lag_insns`, `app_sync_lag_insns`,
//!   `app_update_lag_commit_insns` and the same three `_table_lag_`
//!   (the head's thermal lag on: τ = 600 s and a thermal coefficient on
//!   every sensor; `update` samples 1 ms apart, the short step, what 999
//!   of 1000 samples do; `update_..._commit` 1 s apart, every sample a
//!   committed `expm1f` step, the worst sample),
//!   `ekf_update_insns`, `sqrtf_libm_insns`, `sqrtf_vsqrt_insns`, `reps`).
//!
//! Limits: QEMU counts instructions, not cycles (the M4 pipeline, flash
//! wait states and FPU latencies are not modelled); a count is the same on
//! every run.

use std::collections::BTreeMap;
use std::fs;
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::Command;

use object::read::elf::{ElfFile32, ProgramHeader};
use object::{Object, ObjectSymbol};

/// Flash budget of the firmware image [bytes]: the ACTIVE partition
/// (`src/memory.x` FLASH, docs/firmware.md "Field update: memory layout").
pub const FLASH_BUDGET: u64 = 220 * 1024;
/// Flash budget of the bootloader [bytes]: its 32 KiB region, public key
/// included (`boot/memory.x`).
pub const BOOT_FLASH_BUDGET: u64 = 32 * 1024;
/// Static RAM budget of the firmware [bytes].
pub const RAM_BUDGET: u64 = 48 * 1024;
/// The MPU stack guard at the bottom of the stack (`src/board.rs` `GUARD`) [bytes].
const STACK_GUARD: u64 = 8192;

const TARGET: &str = "thumbv7em-none-eabihf";
const FLASH_RANGE: std::ops::Range<u64> = 0x0800_0000..0x0810_0000;
const RAM_RANGE: std::ops::Range<u64> = 0x2000_0000..0x2010_0000;
/// Repetitions per section in the bench program (`REPS` there).
const BENCH_REPS: u64 = 16;

type Result<T> = std::result::Result<T, String>;

use super::{cargo, root};

#[path = "stack.rs"]
pub mod stack;

fn target_dir() -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root().join("target"))
}

fn run(cmd: &mut Command) -> Result<()> {
    eprintln!("==> {cmd:?}");
    let st = cmd
        .status()
        .map_err(|e| format!("cannot start {cmd:?}: {e}"))?;
    if st.success() {
        Ok(())
    } else {
        Err(format!("{cmd:?} failed ({st})"))
    }
}

/// `cargo xtask fw [--sign KEY] [extra cargo args]` (checks for flip-link,
/// the firmware's linker, first: installs it when missing); with `--sign`,
/// also the signed image for the field update (`sign.rs`).
pub fn fw(args: &[String]) -> Result<()> {
    let linker = super::setup::flip_link()?;
    eprintln!("==> linker: {linker}");
    let (key, rest) = match args.iter().position(|a| a == "--sign") {
        Some(i) => {
            let key = args
                .get(i + 1)
                .ok_or("--sign needs a key file: --sign KEY")?;
            let rest = [&args[..i], &args[i + 2..]].concat();
            (Some(PathBuf::from(key)), rest)
        }
        None => (None, args.to_vec()),
    };
    for package in ["perpend-fw", "perpend-boot"] {
        run(Command::new(cargo())
            .current_dir(root())
            .args(["build", "--release", "--target", TARGET, "-p", package])
            .args(&rest))?;
    }
    match key {
        Some(key) => {
            let elf = target_dir().join(TARGET).join("release").join("perpend-fw");
            crate::sign::sign_elf(&elf, &key).map(|_| ())
        }
        None => Ok(()),
    }
}

/// `_stack_start` (top) and `_stack_end` (bottom) of an ELF image.
pub fn stack_symbols(data: &[u8]) -> Result<(u64, u64)> {
    let elf = object::File::parse(data).map_err(|e| format!("not an ELF: {e}"))?;
    let find = |name: &str| {
        elf.symbols()
            .find(|s| s.name() == Ok(name))
            .map(|s| s.address())
            .ok_or(format!(
                "the image has no `{name}` symbol (not a cortex-m-rt image?)"
            ))
    };
    Ok((find("_stack_start")?, find("_stack_end")?))
}

/// The static worst stack depth of the image at `elf` ([`stack`]).
fn static_depth(elf: &std::path::Path) -> Result<stack::Report> {
    let out = Command::new("llvm-objdump")
        .args(["-d", "--no-show-raw-insn", "--demangle"])
        .arg(elf)
        .output()
        .map_err(|e| format!("llvm-objdump: {e} (Debian: apt-get install llvm)"))?;
    if !out.status.success() {
        return Err(format!("llvm-objdump failed ({})", out.status));
    }
    stack::analyse(&String::from_utf8_lossy(&out.stdout))
}

/// Flash and static RAM use of an ELF image [bytes].
pub fn elf_usage(data: &[u8]) -> Result<(u64, u64)> {
    let elf =
        ElfFile32::<object::Endianness>::parse(data).map_err(|e| format!("not an ELF: {e}"))?;
    let endian = elf.endian();
    let (mut flash, mut ram) = (0u64, 0u64);
    for ph in elf.elf_program_headers() {
        if ph.p_type(endian) != object::elf::PT_LOAD {
            continue;
        }
        let (paddr, vaddr) = (ph.p_paddr(endian) as u64, ph.p_vaddr(endian) as u64);
        if FLASH_RANGE.contains(&paddr) {
            flash += ph.p_filesz(endian) as u64;
        }
        if RAM_RANGE.contains(&vaddr) {
            ram += ph.p_memsz(endian) as u64;
        }
    }
    Ok((flash, ram))
}

/// `cargo xtask size [--no-build]`.
pub fn size(args: &[String]) -> Result<()> {
    if !args.iter().any(|a| a == "--no-build") {
        fw(&[])?;
    }
    let elf = target_dir().join(TARGET).join("release").join("perpend-fw");
    let data = fs::read(&elf).map_err(|e| format!("{}: {e}", elf.display()))?;
    let (flash, ram) = elf_usage(&data)?;
    let pct = |x: u64, b: u64| 100.0 * x as f64 / b as f64;
    println!(
        "perpend-fw: flash {flash} B ({:.1} KiB, {:.0}% of {} KiB), static RAM {ram} B ({:.1} KiB, {:.0}% of {} KiB)",
        flash as f64 / 1024.0,
        pct(flash, FLASH_BUDGET),
        FLASH_BUDGET / 1024,
        ram as f64 / 1024.0,
        pct(ram, RAM_BUDGET),
        RAM_BUDGET / 1024
    );
    let (top, bottom) = stack_symbols(&data)?;
    let stack = top.saturating_sub(bottom);
    println!(
        "stack: {stack} B at {bottom:#010x}..{top:#010x} (flip-link: below .data/.bss), {} B usable above the {STACK_GUARD} B MPU guard",
        stack.saturating_sub(STACK_GUARD)
    );
    let mut over = Vec::new();
    match static_depth(&elf) {
        Ok(r) => {
            let total = r.total();
            let lower = if r.thread.partial || r.handler.partial {
                " (at least: indirect calls/recursion not followed)"
            } else {
                ""
            };
            println!(
                "worst stack depth (static call graph): {total} B{lower} = thread {} B (deepest frame chain ending in {}) + handler {} B ({}, exception frame included); {:.0}% of the usable stack",
                r.thread.bytes,
                r.thread.path.last().map_or("?", String::as_str),
                r.handler.bytes,
                r.handler.path.first().map_or("?", String::as_str),
                pct(total, stack.saturating_sub(STACK_GUARD)),
            );
            if total > stack.saturating_sub(STACK_GUARD) {
                over.push(format!("static stack depth {total} B > usable stack"));
            }
        }
        Err(e) => println!("worst stack depth (static call graph): not measured ({e})"),
    }
    println!("stack used at run time: the painted high-water mark, object 0x200B sub 3 (src/board.rs stack_used)");
    if flash > FLASH_BUDGET {
        over.push(format!("flash {flash} B > {FLASH_BUDGET} B"));
    }
    if ram > RAM_BUDGET {
        over.push(format!("static RAM {ram} B > {RAM_BUDGET} B"));
    }
    over.extend(boot_size()?);
    if over.is_empty() {
        Ok(())
    } else {
        Err(format!("over budget: {}", over.join(", ")))
    }
}

/// Prints the bootloader's flash and static RAM use; what is over budget.
fn boot_size() -> Result<Option<String>> {
    let elf = target_dir()
        .join(TARGET)
        .join("release")
        .join("perpend-boot");
    let data = fs::read(&elf).map_err(|e| {
        format!(
            "{}: {e} (build it: cargo xtask fw, or drop --no-build)",
            elf.display()
        )
    })?;
    let (flash, ram) = elf_usage(&data)?;
    println!(
        "perpend-boot: flash {flash} B ({:.1} KiB, {:.0}% of {} KiB), static RAM {ram} B",
        flash as f64 / 1024.0,
        100.0 * flash as f64 / BOOT_FLASH_BUDGET as f64,
        BOOT_FLASH_BUDGET / 1024,
    );
    Ok((flash > BOOT_FLASH_BUDGET)
        .then(|| format!("bootloader flash {flash} B > {BOOT_FLASH_BUDGET} B")))
}

/// Whether QEMU's option for one instruction per translation block is the
/// 8.1+ spelling.
fn qemu_one_insn_args() -> Result<Vec<&'static str>> {
    let out = Command::new("qemu-system-arm")
        .arg("--version")
        .output()
        .map_err(|e| format!("qemu-system-arm: {e}"))?;
    let text = String::from_utf8_lossy(&out.stdout);
    let ver: Vec<u32> = text
        .split_whitespace()
        .nth(3)
        .unwrap_or("0.0")
        .split(['.', ' ', '('])
        .filter_map(|s| s.parse().ok())
        .collect();
    let new = matches!(ver.as_slice(), [maj, min, ..] if (*maj, *min) >= (8, 1));
    Ok(if new {
        vec!["-accel", "tcg,one-insn-per-tb=on"]
    } else {
        vec!["-singlestep"]
    })
}

/// Per-section instruction counts from a QEMU `-d exec` trace: the number
/// of executed instructions between the entries of `bench_mark` (its own
/// instructions excluded), section `k` = between the `k`-th and `k+1`-th
/// call.
pub fn count_sections(trace: impl BufRead, mark: std::ops::Range<u64>) -> Result<Vec<u64>> {
    let mut sections = Vec::new();
    let mut current: Option<u64> = None;
    for line in trace.lines() {
        let line = line.map_err(|e| format!("trace: {e}"))?;
        // "Trace 0: 0x7f.. [00800408/00001e42/00000110/ff000201] symbol"
        let Some(pc) = line
            .split_once('[')
            .and_then(|(_, r)| r.split('/').nth(1))
            .and_then(|h| u64::from_str_radix(h, 16).ok())
        else {
            continue;
        };
        if pc == mark.start {
            if let Some(n) = current.take() {
                sections.push(n);
            }
            current = Some(0);
        } else if !mark.contains(&pc) {
            if let Some(n) = current.as_mut() {
                *n += 1;
            }
        }
    }
    Ok(sections)
}

/// `cargo xtask mcu-bench [--json]`.
pub fn mcu_bench(args: &[String]) -> Result<()> {
    let json = args.iter().any(|a| a == "--json");
    super::ensure_debian_packages(&[("qemu-system-arm", "qemu-system-arm")])?;
    let dir = root().join("xtask").join("mcu-bench");
    let tdir = target_dir().join("mcu-bench");
    run(Command::new(cargo())
        .current_dir(&dir)
        .env("CARGO_TARGET_DIR", &tdir)
        // Replaces the workspace's target rustflags (which link defmt).
        .env("RUSTFLAGS", "-C link-arg=-Tlink.x -C link-arg=--nmagic")
        .args(["build", "--release", "--target", TARGET]))?;
    let elf_path = tdir.join(TARGET).join("release").join("perpend-mcu-bench");
    let data = fs::read(&elf_path).map_err(|e| format!("{}: {e}", elf_path.display()))?;
    let obj = object::File::parse(&*data).map_err(|e| format!("bench ELF: {e}"))?;
    let mark = obj
        .symbols()
        .find(|s| s.name() == Ok("bench_mark"))
        .ok_or("bench_mark not in the bench ELF")?;
    // Thumb symbols have bit 0 set.
    let start = mark.address() & !1;
    let range = start..start + mark.size().max(2);

    let trace = tdir.join("mcu-bench-trace.log");
    let mut cmd = Command::new("qemu-system-arm");
    cmd.args(["-M", "mps2-an386", "-nographic", "-semihosting-config"])
        .arg("enable=on,target=native")
        .arg("-kernel")
        .arg(&elf_path)
        .args(["-d", "exec,nochain"])
        .args(qemu_one_insn_args()?)
        .arg("-D")
        .arg(&trace);
    // The bench ends with a semihosting exit (status 0 on success).
    run(&mut cmd)?;
    let f = fs::File::open(&trace).map_err(|e| format!("{}: {e}", trace.display()))?;
    let s = count_sections(BufReader::new(f), range)?;
    let _ = fs::remove_file(&trace);
    if s.len() < 33 {
        return Err(format!(
            "expected 33 sections in the trace, found {}",
            s.len()
        ));
    }
    let per = |n: u64| n / BENCH_REPS;
    let base = s[6];
    let mut r = BTreeMap::new();
    r.insert("pipeline_insns", per(s[0]));
    r.insert("ekf_update_insns", per(s[2]));
    r.insert("sqrtf_libm_insns", per(s[4].saturating_sub(base)));
    r.insert("sqrtf_vsqrt_insns", per(s[5].saturating_sub(base)));
    r.insert("pipeline_sphere_insns", per(s[8]));
    r.insert("app_update_insns", per(s[10]));
    r.insert("app_sync_insns", per(s[12]));
    r.insert("pipeline_sphere_steep_insns", per(s[14]));
    r.insert("pipeline_table_insns", per(s[16]));
    r.insert("app_update_table_insns", per(s[18]));
    r.insert("app_sync_table_insns", per(s[20]));
    r.insert("app_update_lag_insns", per(s[22]));
    r.insert("app_sync_lag_insns", per(s[24]));
    r.insert("app_update_lag_commit_insns", per(s[26]));
    r.insert("app_update_table_lag_insns", per(s[28]));
    r.insert("app_sync_table_lag_insns", per(s[30]));
    r.insert("app_update_table_lag_commit_insns", per(s[32]));
    r.insert("reps", BENCH_REPS);
    if json {
        println!(
            "{}",
            serde_json::to_string(&r).map_err(|e| format!("json: {e}"))?
        );
    } else {
        for (k, v) in &r {
            println!("{k:>20}: {v}");
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn sections_between_marks() {
        let t = "\
Trace 0: 0x1 [00800408/00000400/00000110/ff000201] Reset
Trace 0: 0x1 [00800408/00000100/00000110/ff000201] bench_mark
Trace 0: 0x1 [00800408/00000102/00000110/ff000201] bench_mark
Trace 0: 0x1 [00800408/00000500/00000110/ff000201] main
Trace 0: 0x1 [00800408/00000502/00000110/ff000201] main
Trace 0: 0x1 [00800408/00000100/00000110/ff000201] bench_mark
Trace 0: 0x1 [00800408/00000504/00000110/ff000201] main
Trace 0: 0x1 [00800408/00000100/00000110/ff000201] bench_mark
garbage line
";
        let s = count_sections(BufReader::new(t.as_bytes()), 0x100..0x104).unwrap();
        assert_eq!(s, vec![2, 1]);
    }

    #[test]
    fn elf_usage_rejects_garbage() {
        assert!(elf_usage(b"not an elf").is_err());
    }
}

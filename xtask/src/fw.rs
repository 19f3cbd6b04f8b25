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
use object::{Object, ObjectSection, ObjectSymbol};

/// Flash budget of the firmware image [bytes]: the ACTIVE partition
/// (`src/memory.x` FLASH, docs/firmware.md "Field update: memory layout").
pub const FLASH_BUDGET: u64 = 220 * 1024;
/// Issue 50's goal for the image [bytes]: printed with the gap, not yet
/// enforced (136,728 B reached; docs/firmware.md "Budget and speed").
const FLASH_GOAL: u64 = 128 * 1024;
/// Flash budget of the bootloader [bytes]: its 32 KiB region, public key
/// included (`boot/memory.x`).
pub const BOOT_FLASH_BUDGET: u64 = 32 * 1024;
/// Static RAM budget of the firmware [bytes].
pub const RAM_BUDGET: u64 = 48 * 1024;
/// The MPU stack guard at the bottom of the stack (`src/board.rs` `GUARD`) [bytes].
const STACK_GUARD: u64 = 8192;
/// Fail when an f64 soft-float routine is linked (issue 50 item 7).
const ENFORCE_NO_F64: bool = true;
/// Budget of the worst static stack depth [bytes] (issue 50's goal;
/// docs/firmware.md "Stack").
const DEPTH_BUDGET: u64 = 16 * 1024;
/// Every function's own frame stays below this [bytes], roots included
/// (issue 50's goal "no frame > 4 KiB"; well below the guard).
const FRAME_BUDGET: u64 = 4 * 1024;

const TARGET: &str = "thumbv7em-none-eabihf";
const FLASH_RANGE: std::ops::Range<u64> = 0x0800_0000..0x0810_0000;
const RAM_RANGE: std::ops::Range<u64> = 0x2000_0000..0x2010_0000;
/// Repetitions per section in the bench program (`REPS` there).
const BENCH_REPS: u64 = 16;
/// Limit of the App's update + SYNC of the plain configuration (plane
/// model, no table, no lag) [instructions]: issue 50 item 8's goal;
/// `mcu-bench` fails above it (docs/firmware.md "Budget and speed").
const APP_SAMPLE_LIMIT: u64 = 4_000;
/// Limit of the worst App update + SYNC over every configuration the
/// bench runs (linearity tables, thermal lag and its commit)
/// [instructions]: issue 50's goal (3,937 reached, was 4,342);
/// `mcu-bench` fails above it.
const APP_SAMPLE_WORST_LIMIT: u64 = 4_000;
/// Each App update section and the SYNC section of the same App.
const APP_PAIRS: [(&str, &str); 6] = [
    ("app_update_insns", "app_sync_insns"),
    ("app_update_table_insns", "app_sync_table_insns"),
    ("app_update_lag_insns", "app_sync_lag_insns"),
    ("app_update_lag_commit_insns", "app_sync_lag_insns"),
    ("app_update_table_lag_insns", "app_sync_table_lag_insns"),
    (
        "app_update_table_lag_commit_insns",
        "app_sync_table_lag_insns",
    ),
];

/// The App update + SYNC of the plain configuration and the worst over
/// [`APP_PAIRS`] (with the name of its update section).
///
/// # Errors
/// A section is missing from `r`.
pub fn app_sample_cost(r: &BTreeMap<&str, u64>) -> Result<(u64, u64, &'static str)> {
    let get = |k: &str| r.get(k).copied().ok_or(format!("mcu-bench: no {k}"));
    let plain = get(APP_PAIRS[0].0)? + get(APP_PAIRS[0].1)?;
    let mut worst = (0, "");
    for (u, s) in APP_PAIRS {
        let n = get(u)? + get(s)?;
        if n > worst.0 {
            worst = (n, u);
        }
    }
    Ok((plain, worst.0, worst.1))
}

/// Fails when the plain App update + SYNC is above `limit` or the worst
/// above `worst_limit`.
///
/// # Errors
/// Over a limit, or a section missing.
pub fn check_app_sample(
    r: &BTreeMap<&str, u64>,
    limit: u64,
    worst_limit: u64,
) -> Result<(u64, u64)> {
    let (plain, worst, which) = app_sample_cost(r)?;
    if plain > limit {
        return Err(format!(
            "mcu-bench: App update + SYNC {plain} instructions > the limit {limit}"
        ));
    }
    if worst > worst_limit {
        return Err(format!(
            "mcu-bench: App update + SYNC {worst} instructions ({which} + its SYNC) > the limit {worst_limit}"
        ));
    }
    Ok((plain, worst))
}

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

/// The bootloader's key: a release key (`PERPEND_PUBLIC_KEY`) or, only
/// when asked with `--test-key`, the public test key (`perpend-boot`'s
/// feature `test-key`); neither is refused (a release bootloader never
/// gets the test key by accident, issue 50 item 5).
///
/// # Errors
/// Neither a key nor `--test-key`.
pub fn boot_key_args(test_key: bool, release_key: bool) -> Result<Vec<&'static str>> {
    match (release_key, test_key) {
        (true, _) => Ok(vec![]),
        (false, true) => Ok(vec!["--features", "test-key"]),
        (false, false) => Err(
            "no bootloader key: set PERPEND_PUBLIC_KEY=/path/release.pk (a release), \
             or pass --test-key for a TEST build that trusts keys/test-only.pk (CI, development)"
                .into(),
        ),
    }
}

/// `cargo xtask fw [--test-key] [--provision-rom-loader] [--sign KEY
/// [--allow-downgrade]] [extra cargo args]` (checks for flip-link, the
/// firmware's linker, first: installs it when missing); with `--sign`,
/// also the signed image for the field update (`sign.rs`).
pub fn fw(args: &[String]) -> Result<()> {
    let linker = super::setup::flip_link()?;
    eprintln!("==> linker: {linker}");
    let test_key = args.iter().any(|a| a == "--test-key");
    let rom_loader = args.iter().any(|a| a == "--provision-rom-loader");
    let downgrade = args.iter().any(|a| a == "--allow-downgrade");
    let args: Vec<String> = args
        .iter()
        .filter(|a| {
            !matches!(
                a.as_str(),
                "--test-key" | "--provision-rom-loader" | "--allow-downgrade"
            )
        })
        .cloned()
        .collect();
    let mut boot_args = boot_key_args(test_key, std::env::var_os("PERPEND_PUBLIC_KEY").is_some())?;
    if test_key {
        eprintln!("==> TEST build: the bootloader trusts keys/test-only.pk (never ship it)");
    }
    if rom_loader {
        boot_args.extend(["--features", "rom-loader"]);
    }
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
    run(Command::new(cargo())
        .current_dir(root())
        .args(["build", "--release", "--target", TARGET, "-p", "perpend-fw"])
        .args(&rest))?;
    run(Command::new(cargo())
        .current_dir(root())
        .args([
            "build",
            "--release",
            "--target",
            TARGET,
            "-p",
            "perpend-boot",
        ])
        .args(&boot_args)
        .args(&rest))?;
    match key {
        Some(key) => {
            let elf = target_dir().join(TARGET).join("release").join("perpend-fw");
            crate::sign::sign_elf(&elf, &key, downgrade).map(|_| ())
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

/// `cargo xtask size [--no-build] [--test-key]` (`--test-key`: the
/// bootloader is built as a TEST build, see [`fw`]; CI's way).
pub fn size(args: &[String]) -> Result<()> {
    if !args.iter().any(|a| a == "--no-build") {
        let fw_args: Vec<String> = args
            .iter()
            .filter(|a| *a == "--test-key")
            .cloned()
            .collect();
        fw(&fw_args)?;
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
    if flash > FLASH_GOAL {
        println!(
            "flash goal {} KiB (issue 50): {} B over, not met (not enforced)",
            FLASH_GOAL / 1024,
            flash - FLASH_GOAL
        );
    } else {
        println!("flash goal {} KiB (issue 50): met", FLASH_GOAL / 1024);
    }
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
            println!("deepest thread path: {}", path_frames(&r, &r.thread.path));
            let top: Vec<String> = r
                .frames
                .iter()
                .take(5)
                .map(|f| format!("{} {} B", short(&f.0), f.1))
                .collect();
            println!("largest frames (prologues): {}", top.join(", "));
            let fails = stack_budget_failures(&r, STACK_GUARD, FRAME_BUDGET, DEPTH_BUDGET);
            if fails.is_empty() {
                println!(
                    "stack budgets met: every frame < {FRAME_BUDGET} B (largest {} B, below the {STACK_GUARD} B guard), worst depth {total} B <= {DEPTH_BUDGET} B",
                    r.frames.first().map_or(0, |f| f.1)
                );
            }
            over.extend(fails);
        }
        Err(e) => println!("worst stack depth (static call graph): not measured ({e})"),
    }
    println!("stack used at run time: the painted high-water mark, object 0x200B sub 3 (src/board.rs stack_used)");
    let f64s = soft_f64_symbols(&data)?;
    if f64s.is_empty() {
        println!("f64 soft-float routines: none");
    } else {
        println!(
            "f64 soft-float routines: {} ({})",
            f64s.len(),
            f64s.join(", ")
        );
        if ENFORCE_NO_F64 {
            over.push(format!("f64 soft-float in the image: {}", f64s.join(", ")));
        }
    }
    if flash > FLASH_BUDGET {
        over.push(format!("flash {flash} B > {FLASH_BUDGET} B"));
    }
    if ram > RAM_BUDGET {
        over.push(format!("static RAM {ram} B > {RAM_BUDGET} B"));
    }
    over.extend(boot_size()?);
    let boot_elf = target_dir()
        .join(TARGET)
        .join("release")
        .join("perpend-boot");
    if let Ok(boot) = fs::read(&boot_elf) {
        let o = uninit_overlaps(&data, &boot)?;
        if o.is_empty() {
            println!("RAM kept over reset: no application word in perpend-boot's RAM (ROM-loader request in TAMP_BKP0R)");
        }
        over.extend(o);
    }
    if over.is_empty() {
        Ok(())
    } else {
        Err(format!("over budget: {}", over.join(", ")))
    }
}

/// What breaks the stack budgets (empty: all met): a frame at or above
/// the MPU `guard` below the roots (it can step over the guard), any frame
/// (roots included) at or above `frame_budget`, a worst depth (thread +
/// handler) above `depth_budget`.
pub fn stack_budget_failures(
    r: &stack::Report,
    guard: u64,
    frame_budget: u64,
    depth_budget: u64,
) -> Vec<String> {
    let mut fails = Vec::new();
    let (big, _) = stack::frames_over(r, guard);
    for (name, bytes) in big {
        fails.push(format!(
            "frame of {} is {bytes} B >= the {guard} B MPU guard (it can step over it)",
            short(&name)
        ));
    }
    for (name, bytes, _) in r.frames.iter().filter(|f| f.1 >= frame_budget) {
        fails.push(format!(
            "frame of {} is {bytes} B >= the frame budget {frame_budget} B",
            short(name)
        ));
    }
    if r.total() > depth_budget {
        fails.push(format!(
            "static stack depth {} B > budget {depth_budget} B",
            r.total()
        ));
    }
    fails
}

/// `a 8 B > b 276 B > …`: a path with each function's own frame.
fn path_frames(r: &stack::Report, path: &[String]) -> String {
    let frame = |n: &String| r.frames.iter().find(|f| &f.0 == n).map_or(0, |f| f.1);
    path.iter()
        .map(|n| format!("{} {} B", short(n), frame(n)))
        .collect::<Vec<_>>()
        .join(" > ")
}

/// A demangled name without its hash and generic noise, for one line.
fn short(name: &str) -> String {
    let n = name.split("::h").next().unwrap_or(name);
    if n.len() > 90 {
        format!("…{}", &n[n.len() - 89..])
    } else {
        n.to_string()
    }
}

/// Words the application keeps over a reset in RAM (objects in its
/// `.uninit*` sections) that lie in RAM the bootloader's image uses (its
/// `.data`/`.bss`/`.uninit`, zeroed or written by its start-up before the
/// application runs): such a word is lost at every reset (issue 50 item 1:
/// the ROM-loader request at 0x2001_7BFC lay in perpend-boot's `.bss`).
/// defmt-rtt's buffer is left out (scratch, re-initialised at start).
/// Returns the overlaps.
pub fn uninit_overlaps(app: &[u8], boot: &[u8]) -> Result<Vec<String>> {
    let app = object::File::parse(app).map_err(|e| format!("not an ELF: {e}"))?;
    let b = ElfFile32::<object::Endianness>::parse(boot).map_err(|e| format!("not an ELF: {e}"))?;
    let endian = b.endian();
    let boot_ram: Vec<std::ops::Range<u64>> = b
        .elf_program_headers()
        .iter()
        .filter(|ph| ph.p_type(endian) == object::elf::PT_LOAD)
        .map(|ph| {
            let v = u64::from(ph.p_vaddr(endian));
            v..v + u64::from(ph.p_memsz(endian))
        })
        .filter(|r| RAM_RANGE.contains(&r.start) && !r.is_empty())
        .collect();
    let uninit: Vec<std::ops::Range<u64>> = app
        .sections()
        .filter(|s| s.name().is_ok_and(|n| n.starts_with(".uninit")))
        .map(|s| s.address()..s.address() + s.size())
        .collect();
    let mut out = Vec::new();
    for sym in app.symbols() {
        let name = sym.name().unwrap_or("");
        let r = sym.address()..sym.address() + sym.size().max(1);
        if sym.kind() != object::SymbolKind::Data
            || name.contains("defmt_rtt")
            || !uninit.iter().any(|u| u.contains(&r.start))
        {
            continue;
        }
        for br in &boot_ram {
            if r.start < br.end && br.start < r.end {
                out.push(format!(
                    "{} {:#010x}..{:#010x} (kept over reset) lies in perpend-boot's RAM {:#010x}..{:#010x}, which its start-up overwrites",
                    short(name),
                    r.start,
                    r.end,
                    br.start,
                    br.end
                ));
            }
        }
    }
    Ok(out)
}

/// Whether `name` is a compiler-builtins f64 soft-float routine (the
/// Cortex-M4F's FPU is single precision: every `f64` operation calls one).
pub fn is_soft_f64(name: &str) -> bool {
    const AEABI: [&str; 8] = [
        "__aeabi_d",
        "__aeabi_f2d",
        "__aeabi_i2d",
        "__aeabi_ui2d",
        "__aeabi_l2d",
        "__aeabi_ul2d",
        "__aeabi_cdcmp",
        "__aeabi_cdrcmp",
    ];
    const GNU_SUFFIX: [&str; 8] = [
        "df3", "df2", "dfsi", "dfdi", "sidf", "didf", "dfsf2", "sfdf2",
    ];
    AEABI.iter().any(|p| name.starts_with(p))
        || (name.starts_with("__")
            && !name.starts_with("__aeabi")
            && GNU_SUFFIX.iter().any(|s| name.ends_with(s)))
}

/// The f64 soft-float routines linked into an image (sorted, unique).
pub fn soft_f64_symbols(data: &[u8]) -> Result<Vec<String>> {
    let elf = object::File::parse(data).map_err(|e| format!("not an ELF: {e}"))?;
    let mut v: Vec<String> = elf
        .symbols()
        .filter(|s| s.kind() == object::SymbolKind::Text)
        .filter_map(|s| s.name().ok().map(str::to_string))
        .filter(|n| is_soft_f64(n))
        .collect();
    v.sort();
    v.dedup();
    Ok(v)
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
    let checked = check_app_sample(&r, APP_SAMPLE_LIMIT, APP_SAMPLE_WORST_LIMIT);
    if let Ok((plain, worst, _)) = app_sample_cost(&r) {
        r.insert("app_update_sync_insns", plain);
        r.insert("app_update_sync_worst_insns", worst);
        r.insert("app_update_sync_limit_insns", APP_SAMPLE_LIMIT);
        r.insert("app_update_sync_worst_limit_insns", APP_SAMPLE_WORST_LIMIT);
    }
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
    checked.map(|_| ())
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
    fn a_bootloader_without_a_key_is_refused_unless_the_test_key_is_asked_for() {
        let e = boot_key_args(false, false).unwrap_err();
        assert!(
            e.contains("PERPEND_PUBLIC_KEY") && e.contains("--test-key"),
            "{e}"
        );
        assert_eq!(
            boot_key_args(true, false).unwrap(),
            ["--features", "test-key"]
        );
        assert!(boot_key_args(false, true).unwrap().is_empty());
        assert!(
            boot_key_args(true, true).unwrap().is_empty(),
            "the release key wins"
        );
    }

    #[test]
    fn soft_float_names() {
        for n in [
            "__aeabi_dadd",
            "__aeabi_f2d",
            "__aeabi_dcmplt",
            "__adddf3",
            "__extendsfdf2",
            "__truncdfsf2",
            "__floatunsidf",
            "__fixdfsi",
        ] {
            assert!(is_soft_f64(n), "{n}");
        }
        for n in [
            "__aeabi_fadd",
            "__addsf3",
            "__aeabi_memcpy",
            "asinf",
            "__aeabi_uldivmod",
            "sqrtf",
        ] {
            assert!(!is_soft_f64(n), "{n}");
        }
    }

    /// The budgets `size` enforces fail on a frame or a depth above them
    /// (a frame of 4,200 B, as `app::staged_params` had, and a 47 KB depth)
    /// and pass at the figures reached.
    #[test]
    fn stack_budgets_fail_above_them() {
        let frame = |name: &str, bytes: u64, root: bool| (name.to_string(), bytes, root);
        let mut r = stack::Report {
            thread: stack::Depth {
                bytes: 9_060,
                ..Default::default()
            },
            handler: stack::Depth {
                bytes: 1_292,
                ..Default::default()
            },
            frames: vec![
                frame("load_with_tail", 3_184, false),
                frame("task", 880, true),
            ],
        };
        assert!(stack_budget_failures(&r, 8192, 4096, 16384).is_empty());
        r.frames.insert(0, frame("staged_params", 4_200, false));
        let f = stack_budget_failures(&r, 8192, 4096, 16384);
        assert_eq!(f.len(), 1, "{f:?}");
        assert!(
            f[0].contains("staged_params is 4200 B >= the frame budget"),
            "{f:?}"
        );
        r.frames[0] = frame("task", 36_360, true);
        r.thread.bytes = 46_328;
        let f = stack_budget_failures(&r, 8192, 4096, 16384);
        assert_eq!(f.len(), 2, "a root frame counts, the depth too: {f:?}");
        assert!(f[1].contains("depth 47620 B > budget 16384 B"), "{f:?}");
        r.frames[0] = frame("store_now", 9_296, false);
        let f = stack_budget_failures(&r, 8192, 4096, 16384);
        assert!(f[0].contains(">= the 8192 B MPU guard"), "{f:?}");
    }

    /// The bench fails when the worst App update + SYNC is above the
    /// limit: the sections measured before issue 50's speed-up (6,041
    /// with tables, the lag and its commit) fail the old limit of 6,000.
    #[test]
    fn app_sample_limit_fails_above_it() {
        let mut r = BTreeMap::new();
        for (k, v) in [
            ("app_update_insns", 3230),
            ("app_sync_insns", 2321),
            ("app_update_table_insns", 3570),
            ("app_sync_table_insns", 2321),
            ("app_update_lag_insns", 3336),
            ("app_update_lag_commit_insns", 3372),
            ("app_sync_lag_insns", 2321),
            ("app_update_table_lag_insns", 3685),
            ("app_update_table_lag_commit_insns", 3720),
            ("app_sync_table_lag_insns", 2321),
        ] {
            r.insert(k, v);
        }
        assert_eq!(
            app_sample_cost(&r).unwrap(),
            (5551, 6041, "app_update_table_lag_commit_insns")
        );
        let e = check_app_sample(&r, 6000, 6000).unwrap_err();
        assert!(e.contains("6041") && e.contains("6000"), "{e}");
        assert_eq!(check_app_sample(&r, 6000, 6041).unwrap(), (5551, 6041));
        let e = check_app_sample(&r, APP_SAMPLE_LIMIT, APP_SAMPLE_WORST_LIMIT).unwrap_err();
        assert!(e.contains("5551") && e.contains("4000"), "{e}");
        r.remove("app_sync_lag_insns");
        assert!(
            check_app_sample(&r, 10_000, 10_000).is_err(),
            "a missing section fails"
        );
    }

    /// The worst configuration's limit is the goal of 4,000: the sections
    /// measured after the first half of issue 50 (plain 3,854, worst 4,342
    /// with tables, the lag and its commit) fail it, those of its second
    /// half (3,450 and 3,937) pass.
    #[test]
    fn worst_configuration_limit_is_the_goal() {
        let sections = |u: [u64; 6], sync: u64| {
            let names = [
                "app_update_insns",
                "app_update_table_insns",
                "app_update_lag_insns",
                "app_update_lag_commit_insns",
                "app_update_table_lag_insns",
                "app_update_table_lag_commit_insns",
            ];
            let mut r: BTreeMap<&str, u64> = names.into_iter().zip(u).collect();
            for k in [
                "app_sync_insns",
                "app_sync_table_insns",
                "app_sync_lag_insns",
                "app_sync_table_lag_insns",
            ] {
                r.insert(k, sync);
            }
            r
        };
        let before = sections([2535, 2874, 2641, 2675, 2989, 3023], 1319);
        let e = check_app_sample(&before, APP_SAMPLE_LIMIT, APP_SAMPLE_WORST_LIMIT).unwrap_err();
        assert!(e.contains("4342") && e.contains("4000"), "{e}");
        let after = sections([2176, 2515, 2278, 2315, 2627, 2663], 1274);
        assert_eq!(
            check_app_sample(&after, APP_SAMPLE_LIMIT, APP_SAMPLE_WORST_LIMIT).unwrap(),
            (3450, 3937)
        );
    }

    #[test]
    fn elf_usage_rejects_garbage() {
        assert!(elf_usage(b"not an elf").is_err());
    }
}

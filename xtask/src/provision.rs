//! `cargo xtask provision [--test-key] [--allow-rom-loader] [--rdp1]
//! [--dry-run]`: a new board from the factory to a field-ready one, with
//! probe-rs (issue 50, docs/bring-up.md §2):
//!
//! 1. probe-rs installed and a probe attached, else it says so and exits
//!    [`crate::hil::EXIT_NO_PROBE`] / [`crate::hil::EXIT_NO_PROBE_RS`];
//! 2. builds the images (`cargo xtask fw`: a release key from
//!    `PERPEND_PUBLIC_KEY`, or `--test-key`; `--allow-rom-loader` builds
//!    the bootloader with the provisioning flag `rom-loader`);
//! 3. option bytes (RM0440 §3.4 "FLASH option bytes", programming sequence
//!    §3.4.2): DBANK = 1, BFB2 = 0 in FLASH_OPTR (§3.7.8), through the
//!    flash registers at 0x4002_2000 (KEYR, OPTKEYR unlock, OPTSTRT, BSY,
//!    OBL_LAUNCH reloads them with a reset);
//! 4. flashes perpend-boot and perpend-fw (`probe-rs download --verify`:
//!    read back and compared);
//! 5. write-protects the bootloader pages 0-15 (FLASH_WRP1AR, §3.7.11:
//!    WRP1A_STRT = 0, WRP1A_END = 15, key and boot info included);
//! 6. with `--rdp1` only: readout protection level 1 (RDP = 0xBB): no more
//!    debug access to flash; back to level 0 only with a mass erase;
//! 7. reads the option bytes back and compares them with the plan.
//!
//! `--dry-run` prints the plan (register writes) without a probe.
//! How to undo each step: docs/bring-up.md §2.
//!
//! Limits: not run on a board yet; probe-rs's `write`/`read` commands
//! halt the core for each access (harmless on a board being provisioned).

use std::process::Command;

use super::Result;

const CHIP: &str = "STM32G474RETx";
const TARGET: &str = "thumbv7em-none-eabihf";

/// FLASH registers (RM0440 §3.7, base 0x4002_2000).
pub const FLASH_KEYR: u32 = 0x4002_2008;
/// FLASH_OPTKEYR.
pub const FLASH_OPTKEYR: u32 = 0x4002_200C;
/// FLASH_SR (BSY = bit 16).
pub const FLASH_SR: u32 = 0x4002_2010;
/// FLASH_CR (OPTSTRT = bit 17, OBL_LAUNCH = bit 27).
pub const FLASH_CR: u32 = 0x4002_2014;
/// FLASH_OPTR.
pub const FLASH_OPTR: u32 = 0x4002_2020;
/// FLASH_WRP1AR.
pub const FLASH_WRP1AR: u32 = 0x4002_202C;
/// Unlock keys of FLASH_KEYR and FLASH_OPTKEYR.
pub const KEYS: [u32; 2] = [0x4567_0123, 0xCDEF_89AB];
/// Unlock keys of FLASH_OPTKEYR.
pub const OPT_KEYS: [u32; 2] = [0x0819_2A3B, 0x4C5D_6E7F];
/// FLASH_CR.OPTSTRT.
pub const CR_OPTSTRT: u32 = 1 << 17;
/// FLASH_CR.OBL_LAUNCH.
pub const CR_OBL_LAUNCH: u32 = 1 << 27;
/// FLASH_OPTR.DBANK.
pub const OPTR_DBANK: u32 = 1 << 22;
/// FLASH_OPTR.BFB2.
pub const OPTR_BFB2: u32 = 1 << 20;
/// RDP level 0 / level 1 bytes.
pub const RDP0: u32 = 0xAA;
/// Any value but 0xAA and 0xCC is level 1; 0xBB by convention.
pub const RDP1: u32 = 0xBB;
/// Bootloader pages (2 KiB each in dual-bank mode): 0..=15.
pub const WRP_PAGES: (u32, u32) = (0, 15);

/// What the board's option bytes should become.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Target {
    /// FLASH_OPTR.
    pub optr: u32,
    /// FLASH_WRP1AR.
    pub wrp1ar: u32,
}

/// The option bytes for a board whose FLASH_OPTR reads `optr`: DBANK = 1,
/// BFB2 = 0, RDP 0xBB with `rdp1` (else unchanged), everything else kept;
/// WRP area A over the bootloader pages.
pub fn target(optr: u32, wrp1ar: u32, rdp1: bool) -> Target {
    let mut o = (optr | OPTR_DBANK) & !OPTR_BFB2;
    if rdp1 {
        o = (o & !0xFF) | RDP1;
    }
    let w = (wrp1ar & !(0x7F | (0x7F << 16))) | WRP_PAGES.0 | (WRP_PAGES.1 << 16);
    Target { optr: o, wrp1ar: w }
}

/// The register writes that program `optr`/`wrp1ar` (unlock, values,
/// OPTSTRT); the caller waits for BSY and launches the reload.
pub fn option_writes(t: &Target) -> Vec<(u32, u32)> {
    vec![
        (FLASH_KEYR, KEYS[0]),
        (FLASH_KEYR, KEYS[1]),
        (FLASH_OPTKEYR, OPT_KEYS[0]),
        (FLASH_OPTKEYR, OPT_KEYS[1]),
        (FLASH_OPTR, t.optr),
        (FLASH_WRP1AR, t.wrp1ar),
        (FLASH_CR, CR_OPTSTRT),
    ]
}

/// The options of `provision`.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Options {
    /// TEST build: the bootloader trusts keys/test-only.pk.
    pub test_key: bool,
    /// The bootloader's provisioning flag for the ROM loader.
    pub allow_rom_loader: bool,
    /// Readout protection level 1.
    pub rdp1: bool,
    /// Print the plan only.
    pub dry_run: bool,
}

/// Parses the arguments.
///
/// # Errors
/// An unknown option.
pub fn options(args: &[String]) -> Result<Options> {
    let mut o = Options::default();
    for a in args {
        match a.as_str() {
            "--test-key" => o.test_key = true,
            "--allow-rom-loader" => o.allow_rom_loader = true,
            "--rdp1" => o.rdp1 = true,
            "--dry-run" => o.dry_run = true,
            _ => {
                return Err(format!(
                    "provision: unknown option {a} (known: --test-key, --allow-rom-loader, --rdp1, --dry-run)"
                ))
            }
        }
    }
    Ok(o)
}

fn hex(v: u32) -> String {
    format!("{v:#010x}")
}

/// `probe-rs write b32 ADDR VALUE`.
fn write(addr: u32, value: u32) -> Result<()> {
    super::run(
        "probe-rs",
        &["write", "--chip", CHIP, "b32", &hex(addr), &hex(value)],
    )
}

/// `probe-rs read b32 ADDR 1`: the word.
fn read(addr: u32) -> Result<u32> {
    let out = Command::new("probe-rs")
        .args(["read", "--chip", CHIP, "b32", &hex(addr), "1"])
        .output()
        .map_err(|e| format!("probe-rs read: {e}"))?;
    if !out.status.success() {
        return Err(format!(
            "probe-rs read {} failed: {}",
            hex(addr),
            String::from_utf8_lossy(&out.stderr)
        ));
    }
    parse_word(&String::from_utf8_lossy(&out.stdout))
        .ok_or_else(|| format!("probe-rs read {}: no word in its output", hex(addr)))
}

/// The first hexadecimal word of probe-rs's `read` output (`a2eff8aa`).
pub fn parse_word(text: &str) -> Option<u32> {
    text.split_whitespace()
        .map(|w| w.trim_start_matches("0x"))
        .find_map(|w| u32::from_str_radix(w, 16).ok())
}

/// `cargo xtask provision` (module docs).
pub fn provision(args: &[String]) -> Result<()> {
    let o = options(args)?;
    let mut fw_args: Vec<String> = Vec::new();
    if o.test_key {
        fw_args.push("--test-key".into());
    }
    if o.allow_rom_loader {
        fw_args.push("--provision-rom-loader".into());
    }
    if o.dry_run {
        let t = target(0xFFEF_F8AA, 0xFF00_FFFF, o.rdp1);
        println!("provision plan (factory option bytes assumed; --dry-run):");
        println!("  1. build: cargo xtask fw {}", fw_args.join(" "));
        println!(
            "  2. option bytes: FLASH_OPTR -> {} (DBANK = 1, BFB2 = 0{})",
            hex(t.optr),
            if o.rdp1 { ", RDP level 1 later" } else { "" }
        );
        for (a, v) in option_writes(&Target {
            optr: t.optr & !0xFF | RDP0,
            wrp1ar: 0xFF00_FFFF,
        }) {
            println!("     write {} = {}", hex(a), hex(v));
        }
        println!(
            "     wait FLASH_SR.BSY = 0, write FLASH_CR = {} (OBL_LAUNCH: reload, reset)",
            hex(CR_OBL_LAUNCH)
        );
        println!("  3. probe-rs download --verify perpend-boot, perpend-fw");
        println!(
            "  4. FLASH_WRP1AR -> {} (pages {}..={})",
            hex(t.wrp1ar),
            WRP_PAGES.0,
            WRP_PAGES.1
        );
        if o.rdp1 {
            println!("  5. FLASH_OPTR RDP -> 0xBB (level 1)");
        }
        println!("  6. read FLASH_OPTR and FLASH_WRP1AR back and compare");
        return Ok(());
    }
    if let Some(why) = super::hil::probe_missing() {
        let (line, status) = why.report();
        println!("{}", line.replacen("hil:", "provision:", 1));
        std::process::exit(status);
    }
    super::fw::fw(&fw_args)?;
    let optr = read(FLASH_OPTR)?;
    let wrp = read(FLASH_WRP1AR)?;
    println!(
        "option bytes before: FLASH_OPTR {} FLASH_WRP1AR {}",
        hex(optr),
        hex(wrp)
    );
    let t = target(optr, wrp, o.rdp1);
    // DBANK/BFB2 first, RDP and WRP unchanged (the pages must be writable).
    let stage1 = Target {
        optr: t.optr & !0xFF | (optr & 0xFF),
        wrp1ar: wrp,
    };
    program(&stage1)?;
    let dir = super::root().join("target").join(TARGET).join("release");
    for elf in ["perpend-boot", "perpend-fw"] {
        let p = dir.join(elf);
        super::run(
            "probe-rs",
            &["download", "--chip", CHIP, "--verify", &p.to_string_lossy()],
        )?;
    }
    program(&Target {
        optr: stage1.optr,
        wrp1ar: t.wrp1ar,
    })?;
    if o.rdp1 {
        program(&t)?;
    }
    let (optr2, wrp2) = (read(FLASH_OPTR)?, read(FLASH_WRP1AR)?);
    println!(
        "option bytes after: FLASH_OPTR {} FLASH_WRP1AR {}",
        hex(optr2),
        hex(wrp2)
    );
    if (optr2 & (OPTR_DBANK | OPTR_BFB2 | 0xFF)) != (t.optr & (OPTR_DBANK | OPTR_BFB2 | 0xFF))
        || (wrp2 & 0x007F_007F) != (t.wrp1ar & 0x007F_007F)
    {
        return Err("provision: the option bytes read back differ from the plan".into());
    }
    println!("provision: done (bootloader and application verified, option bytes as planned)");
    Ok(())
}

/// Programs the option bytes and reloads them (the part resets).
fn program(t: &Target) -> Result<()> {
    for (a, v) in option_writes(t) {
        write(a, v)?;
    }
    for _ in 0..100 {
        if read(FLASH_SR)? & (1 << 16) == 0 {
            // OBL_LAUNCH resets the part: probe-rs may report the lost
            // connection, which is expected.
            let _ = write(FLASH_CR, CR_OBL_LAUNCH);
            std::thread::sleep(std::time::Duration::from_millis(500));
            return Ok(());
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    Err("provision: FLASH_SR.BSY stayed set after OPTSTRT".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_single_bank_board_gets_dual_bank_boot_from_bank_1_and_wrp() {
        // DBANK = 0, BFB2 = 1 (a mistake), RDP 0
        let optr = (0xFFEF_F8AA & !OPTR_DBANK) | OPTR_BFB2;
        let t = target(optr, 0xFF00_FFFF, false);
        assert_eq!(t.optr, 0xFFEF_F8AA, "factory value back");
        assert_eq!(t.wrp1ar & 0x007F_007F, 15 << 16);
        assert_eq!(target(0xFFEF_F8AA, 0xFF00_FFFF, true).optr & 0xFF, RDP1);
        let w = option_writes(&t);
        assert_eq!(
            w[..4],
            [
                (FLASH_KEYR, KEYS[0]),
                (FLASH_KEYR, KEYS[1]),
                (FLASH_OPTKEYR, OPT_KEYS[0]),
                (FLASH_OPTKEYR, OPT_KEYS[1])
            ]
        );
        assert_eq!(w.last(), Some(&(FLASH_CR, CR_OPTSTRT)));
    }

    #[test]
    fn options_and_probe_rs_output() {
        let o = options(&["--test-key".into(), "--rdp1".into()]).unwrap();
        assert!(o.test_key && o.rdp1 && !o.allow_rom_loader);
        assert!(options(&["--rdp2".into()]).is_err());
        assert_eq!(parse_word("ffeff8aa\n"), Some(0xFFEF_F8AA));
        assert_eq!(parse_word("0x40022020: ffeff8aa"), Some(0xFFEF_F8AA));
    }
}

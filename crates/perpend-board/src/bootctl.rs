//! Boot control of the sensor board (issue 50 items 1, 2, 4, 5): the
//! request to enter the STM32 ROM loader, the watchdog hand-over from the
//! bootloader to the application, the option-byte check the bootloader
//! makes before it lets embassy's flash driver near the flash, and the
//! bootloader's build flags the application reads. Pure logic over small
//! register traits; `boot/src/main.rs` and `src/board.rs` implement the
//! traits on the registers, the tests here on fakes.
//!
//! * **ROM-loader request** ([`request_rom_loader`],
//!   [`take_rom_loader_request`]): the application writes
//!   [`ROM_LOADER_MAGIC`] into TAMP_BKP0R and resets; the bootloader reads
//!   and clears it before anything else, and enters the ROM loader only
//!   when its [`RomLoaderPolicy`] allows. The tamper backup registers keep
//!   their contents over a system reset (RM0440, TAMP chapter, "TAMP backup
//!   registers": reset only by a backup-domain reset or a tamper event,
//!   kept while VDD or VBAT is present); writes need the backup domain
//!   unlocked (PWR_CR1.DBP, RM0440 §6.4.1) and the RTC/TAMP APB clock
//!   (RCC_APB1ENR1.RTCAPBEN). No RAM word is used: the bootloader's
//!   start-up code zeroes its own `.bss`, which lay over the word the
//!   application used before (0x2001_7BFC, issue 50 item 1).
//!   embassy-stm32 0.6's `Rtc::read_backup_register` returns `None` on the
//!   G4 (RTC v3: "backup registers come from the TAMP peripheral", left
//!   unimplemented), so the firmware writes TAMP_BKP0R through the PAC.
//! * **Policy** ([`RomLoaderPolicy`], [`BootInfo`]): a bootloader built
//!   with the public test key (cargo feature `test-key`) or with the
//!   provisioning flag (cargo feature `rom-loader`, `cargo xtask provision
//!   --allow-rom-loader`) allows the entry; a release bootloader without
//!   the flag refuses it, because the ROM loader writes unsigned code (RDP
//!   level 0, WRP only over the bootloader). The bootloader publishes its
//!   flags next to its public key ([`BootInfo`], 0x0800_7FD8), where the
//!   application reads them to refuse the 0x2500 command at once.
//! * **Watchdog hand-over** ([`handover`]): the bootloader leaves the IWDG
//!   running at /256, reload 1000 (8 s). Writing a new prescaler does not
//!   reload the counter (RM0440 §42.3, IWDG functional description, and
//!   §42.4.1 IWDG_KR: only the key 0xAAAA reloads it), so the
//!   counter's remaining ticks run at the new rate: /4 after /256 left
//!   1000 ticks at 8 kHz = 125 ms (embassy-stm32 0.6
//!   `IndependentWatchdog::new` writes PR and RLR without a reload). The
//!   hand-over waits until PVU/RVU are clear (the values reached the LSI
//!   domain) and then reloads: the full new timeout from that instant.
//! * **Option bytes** ([`check_option_bytes`]): FLASH_OPTR (RM0440 §3.7.8)
//!   must have DBANK = 1 (two banks of 2 KiB pages, the layout of
//!   `boot/memory.x`) and BFB2 = 0 (boot from bank 1). embassy-stm32 0.6's
//!   `Flash::new_blocking` panics when DBANK = 0 under its `dual-bank`
//!   feature (`flash/g.rs` `check_bank_setup`), which reset the board for
//!   ever. The bootloader now checks first: with wrong option bytes it
//!   logs them (RTT), never creates the flash driver, swaps nothing and
//!   starts the application, which refuses every flash write and reports
//!   [`EMCY_OPTION_BYTES`].

/// Errors of boot control.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BootCtlError {
    /// The bootloader does not allow the ROM loader (a release build
    /// without the provisioning flag, or no bootloader).
    RomLoaderLocked,
    /// The IWDG did not take the new prescaler/reload (PVU/RVU stayed
    /// set); the watchdog runs on with its old setting.
    WatchdogBusy,
    /// No IWDG setting gives this timeout (below 125 µs or above 32.7 s).
    WatchdogTimeout,
    /// FLASH_OPTR.DBANK = 0: single bank, 4 KiB pages; the layout needs
    /// two banks of 2 KiB pages.
    SingleBank,
    /// FLASH_OPTR.BFB2 = 1: the part boots from bank 2, the addresses of
    /// the two banks swap under the bootloader.
    BootFromBank2,
}

// ---------------------------------------------------------------------------
// ROM-loader request

/// The request word in TAMP_BKP0R ("BOOT" + "LOAD").
pub const ROM_LOADER_MAGIC: u32 = 0xB007_10AD;
/// The backup register the request lives in (TAMP_BKP0R).
pub const ROM_LOADER_BKP: usize = 0;

/// A 32-bit register that keeps its value over a system reset (TAMP_BKPxR).
pub trait BackupRegister {
    /// Reads the register.
    fn read(&mut self) -> u32;
    /// Writes the register.
    fn write(&mut self, value: u32);
}

/// Whether this bootloader lets the application into the ROM loader.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct RomLoaderPolicy {
    /// Built with the public test key (a development build).
    pub test_key: bool,
    /// Built with the provisioning flag (cargo feature `rom-loader`).
    pub provisioned: bool,
}

impl RomLoaderPolicy {
    /// Entry allowed: a test-key build, or a release with the flag.
    pub const fn allows(self) -> bool {
        self.test_key || self.provisioned
    }
}

/// What the bootloader does with the request word at reset.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RomLoader {
    /// No request: boot as usual.
    None,
    /// A request, allowed: jump to the ROM loader.
    Enter,
    /// A request the policy refuses: boot as usual (logged).
    Refused,
}

/// Application side: asks for the ROM loader at the next reset.
///
/// # Errors
/// [`BootCtlError::RomLoaderLocked`] when `policy` refuses it (nothing is
/// written).
pub fn request_rom_loader(
    reg: &mut impl BackupRegister,
    policy: RomLoaderPolicy,
) -> Result<(), BootCtlError> {
    if !policy.allows() {
        return Err(BootCtlError::RomLoaderLocked);
    }
    reg.write(ROM_LOADER_MAGIC);
    Ok(())
}

/// Bootloader side, first thing after reset: reads and clears the request
/// (a request is taken once, whatever follows) and decides.
pub fn take_rom_loader_request(
    reg: &mut impl BackupRegister,
    policy: RomLoaderPolicy,
) -> RomLoader {
    let v = reg.read();
    if v == 0 {
        return RomLoader::None;
    }
    reg.write(0);
    match (v == ROM_LOADER_MAGIC, policy.allows()) {
        (false, _) => RomLoader::None,
        (true, true) => RomLoader::Enter,
        (true, false) => RomLoader::Refused,
    }
}

// ---------------------------------------------------------------------------
// Bootloader build flags

/// Where the bootloader puts its [`BootInfo`] (8 bytes below the key).
pub const BOOT_INFO_ADDR: u32 = 0x0800_7FD8;
/// Magic of the [`BootInfo`] words ("PBI1").
pub const BOOT_INFO_MAGIC: u32 = u32::from_le_bytes(*b"PBI1");
/// [`BootInfo`] flag: built with the public test key.
pub const FLAG_TEST_KEY: u32 = 1 << 0;
/// [`BootInfo`] flag: the ROM loader may be entered (provisioning flag).
pub const FLAG_ROM_LOADER: u32 = 1 << 1;

/// The bootloader's build flags as the application reads them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct BootInfo {
    /// `FLAG_*` bits.
    pub flags: u32,
}

impl BootInfo {
    /// The two words the bootloader stores.
    pub const fn words(self) -> [u32; 2] {
        [BOOT_INFO_MAGIC, self.flags]
    }

    /// Parses the two words; `None` without the magic (no bootloader,
    /// erased flash, or an older bootloader: everything refused).
    pub fn from_words(w: [u32; 2]) -> Option<Self> {
        (w[0] == BOOT_INFO_MAGIC).then_some(Self { flags: w[1] })
    }

    /// The policy these flags describe.
    pub const fn policy(self) -> RomLoaderPolicy {
        RomLoaderPolicy {
            test_key: self.flags & FLAG_TEST_KEY != 0,
            provisioned: self.flags & FLAG_ROM_LOADER != 0,
        }
    }
}

// ---------------------------------------------------------------------------
// IWDG hand-over

/// IWDG_KR: reload the counter (RM0440 §42.4.1).
pub const KEY_RELOAD: u16 = 0xAAAA;
/// IWDG_KR: unlock IWDG_PR, IWDG_RLR, IWDG_WINR.
pub const KEY_UNLOCK: u16 = 0x5555;
/// IWDG_KR: start the watchdog.
pub const KEY_START: u16 = 0xCCCC;
/// LSI frequency the timeouts are computed with [Hz] (RM0440: 32 kHz).
pub const LSI_HZ: u32 = 32_000;
/// Largest reload value (12 bits).
pub const MAX_RELOAD: u16 = 0xFFF;
/// Polls of IWDG_SR before [`handover`] gives up (PVU/RVU clear within a
/// few LSI periods, RM0440 §42.4.4 IWDG_SR; this is over 1 ms at 170 MHz).
pub const SR_POLLS: u32 = 200_000;

/// The IWDG registers the hand-over writes.
pub trait IwdgRegs {
    /// Writes IWDG_KR.
    fn key(&mut self, key: u16);
    /// Writes IWDG_PR (0 = /4 … 6 = /256).
    fn set_prescaler(&mut self, pr: u8);
    /// Writes IWDG_RLR.
    fn set_reload(&mut self, rl: u16);
    /// IWDG_SR.PVU | RVU | WVU: an update is still on its way.
    fn busy(&mut self) -> bool;
}

/// A prescaler (IWDG_PR) and reload (IWDG_RLR) pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IwdgSetting {
    /// IWDG_PR: divider 4 << pr.
    pub pr: u8,
    /// IWDG_RLR.
    pub rl: u16,
}

impl IwdgSetting {
    /// The bootloader's setting: /256, reload 1000 (8.008 s).
    pub const BOOTLOADER: Self = Self { pr: 6, rl: 1000 };

    /// The smallest prescaler whose reload reaches `timeout_us`.
    ///
    /// # Errors
    /// [`BootCtlError::WatchdogTimeout`] for 0 or more than /256 with
    /// reload 0xFFF gives (32.7 s).
    pub fn for_timeout_us(timeout_us: u32) -> Result<Self, BootCtlError> {
        for pr in 0..=6u8 {
            let div = 4u64 << pr;
            let ticks = u64::from(timeout_us) * u64::from(LSI_HZ) / (div * 1_000_000);
            if (1..=u64::from(MAX_RELOAD) + 1).contains(&ticks) {
                return Ok(Self {
                    pr,
                    rl: (ticks - 1) as u16,
                });
            }
        }
        Err(BootCtlError::WatchdogTimeout)
    }

    /// The timeout a full counter gives [µs] (RLR + 1 ticks, as
    /// embassy-stm32's `get_timeout_us`).
    pub fn timeout_us(self) -> u32 {
        let div = 4u64 << self.pr;
        ((u64::from(self.rl) + 1) * div * 1_000_000 / u64::from(LSI_HZ)) as u32
    }
}

/// Hands the running IWDG over to `to`: unlock, prescaler, reload value,
/// wait for PVU/RVU, then reload the counter (the full new timeout starts
/// now). Also starts a stopped watchdog.
///
/// # Errors
/// [`BootCtlError::WatchdogBusy`] when the update never completed; the
/// counter is reloaded anyway (with whatever setting the IWDG holds).
pub fn handover(regs: &mut impl IwdgRegs, to: IwdgSetting) -> Result<(), BootCtlError> {
    regs.key(KEY_START);
    regs.key(KEY_UNLOCK);
    regs.set_prescaler(to.pr);
    regs.set_reload(to.rl);
    let mut done = false;
    for _ in 0..SR_POLLS {
        if !regs.busy() {
            done = true;
            break;
        }
    }
    regs.key(KEY_RELOAD);
    if done {
        Ok(())
    } else {
        Err(BootCtlError::WatchdogBusy)
    }
}

// ---------------------------------------------------------------------------
// Option bytes

/// FLASH_OPTR.DBANK (bit 22).
pub const OPTR_DBANK: u32 = 1 << 22;
/// FLASH_OPTR.BFB2 (bit 20).
pub const OPTR_BFB2: u32 = 1 << 20;
/// FLASH_OPTR.nSWBOOT0 (bit 26).
pub const OPTR_NSWBOOT0: u32 = 1 << 26;
/// FLASH_OPTR.nBOOT0 (bit 27).
pub const OPTR_NBOOT0: u32 = 1 << 27;
/// FLASH_OPTR.RDP (bits 0..7): 0xAA = level 0.
pub const OPTR_RDP_MASK: u32 = 0xFF;

/// EMCY of wrong option bytes (CiA 301 0x5000 "device hardware"); data
/// `[1, OPTR byte 2, OPTR byte 3, RDP, 0]` (DBANK is bit 6 of byte 2, BFB2
/// bit 4). Raised at boot and kept: the board writes no flash until the
/// option bytes are fixed (docs/bring-up.md §2).
pub const EMCY_OPTION_BYTES: u16 = 0x5000;

/// Checks the option bytes the flash layout needs (module docs).
///
/// # Errors
/// [`BootCtlError::SingleBank`] or [`BootCtlError::BootFromBank2`].
pub fn check_option_bytes(optr: u32) -> Result<(), BootCtlError> {
    if optr & OPTR_DBANK == 0 {
        return Err(BootCtlError::SingleBank);
    }
    if optr & OPTR_BFB2 != 0 {
        return Err(BootCtlError::BootFromBank2);
    }
    Ok(())
}

/// The EMCY data of [`EMCY_OPTION_BYTES`] for `optr`.
pub fn option_bytes_emcy_data(optr: u32) -> [u8; 5] {
    let b = optr.to_le_bytes();
    [1, b[2], b[3], b[0], 0]
}

/// What the bootloader does after the option-byte check.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BootPlan {
    /// Option bytes right: embassy-boot's `prepare` (swap or revert),
    /// then the application.
    Update,
    /// Option bytes wrong: no flash driver, no swap; the application
    /// starts as it is and reports the fault.
    StartOnly(BootCtlError),
}

/// The bootloader's plan for `optr`.
pub fn boot_plan(optr: u32) -> BootPlan {
    match check_option_bytes(optr) {
        Ok(()) => BootPlan::Update,
        Err(e) => BootPlan::StartOnly(e),
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
#[path = "bootctl_tests.rs"]
mod tests;

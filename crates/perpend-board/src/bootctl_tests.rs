//! Tests of `bootctl.rs` on fakes of TAMP_BKP0R and the IWDG.

use super::*;

/// TAMP_BKP0R: keeps its value over a system reset (a backup-domain
/// reset, not modelled, would clear it).
#[derive(Default)]
struct Bkp(u32);

impl BackupRegister for Bkp {
    fn read(&mut self) -> u32 {
        self.0
    }
    fn write(&mut self, value: u32) {
        self.0 = value;
    }
}

const DEV: RomLoaderPolicy = RomLoaderPolicy {
    test_key: true,
    provisioned: false,
};
const RELEASE: RomLoaderPolicy = RomLoaderPolicy {
    test_key: false,
    provisioned: false,
};
const PROVISIONED: RomLoaderPolicy = RomLoaderPolicy {
    test_key: false,
    provisioned: true,
};

#[test]
fn a_request_survives_the_reset_and_is_taken_once() {
    let mut r = Bkp::default();
    assert_eq!(take_rom_loader_request(&mut r, DEV), RomLoader::None);
    request_rom_loader(&mut r, DEV).unwrap();
    // system reset: the register keeps its value; the bootloader reads it
    // before its own start-up touches anything else
    assert_eq!(take_rom_loader_request(&mut r, DEV), RomLoader::Enter);
    assert_eq!(r.0, 0, "cleared: the ROM loader's own reset boots normally");
    assert_eq!(take_rom_loader_request(&mut r, DEV), RomLoader::None);
}

#[test]
fn a_release_bootloader_refuses_the_rom_loader_unless_provisioned() {
    let mut r = Bkp::default();
    assert_eq!(
        request_rom_loader(&mut r, RELEASE),
        Err(BootCtlError::RomLoaderLocked)
    );
    assert_eq!(r.0, 0, "nothing written");
    // a request left by an older application (or written by a debugger)
    r.0 = ROM_LOADER_MAGIC;
    assert_eq!(take_rom_loader_request(&mut r, RELEASE), RomLoader::Refused);
    assert_eq!(r.0, 0, "taken: no loop of refusals");
    request_rom_loader(&mut r, PROVISIONED).unwrap();
    assert_eq!(
        take_rom_loader_request(&mut r, PROVISIONED),
        RomLoader::Enter
    );
}

#[test]
fn garbage_in_the_register_is_no_request() {
    for v in [1, 0xFFFF_FFFF, ROM_LOADER_MAGIC ^ 1] {
        let mut r = Bkp(v);
        assert_eq!(take_rom_loader_request(&mut r, DEV), RomLoader::None);
        assert_eq!(r.0, 0);
    }
}

#[test]
fn boot_info_words_carry_the_policy() {
    let i = BootInfo {
        flags: FLAG_TEST_KEY,
    };
    assert_eq!(BootInfo::from_words(i.words()), Some(i));
    assert_eq!(i.policy(), DEV);
    let p = BootInfo {
        flags: FLAG_ROM_LOADER,
    };
    assert!(p.policy().allows());
    assert!(!BootInfo { flags: 0 }.policy().allows());
    // erased flash (no bootloader) or an older bootloader: refused
    assert_eq!(BootInfo::from_words([0xFFFF_FFFF; 2]), None);
}

/// The IWDG as far as the hand-over sees it: the counter keeps its ticks
/// when the prescaler changes and is reloaded only by the 0xAAAA key.
struct Iwdg {
    running: bool,
    unlocked: bool,
    pr: u8,
    rl: u16,
    counter: u16,
    busy_polls: u32,
}

impl Iwdg {
    /// As the bootloader leaves it: /256, reload 1000, just fed.
    fn from_bootloader() -> Self {
        Self {
            running: true,
            unlocked: false,
            pr: IwdgSetting::BOOTLOADER.pr,
            rl: IwdgSetting::BOOTLOADER.rl,
            counter: IwdgSetting::BOOTLOADER.rl,
            busy_polls: 3,
        }
    }
    /// Time until the reset [µs].
    fn left_us(&self) -> u64 {
        (u64::from(self.counter) + 1) * (4u64 << self.pr) * 1_000_000 / u64::from(LSI_HZ)
    }
}

impl IwdgRegs for Iwdg {
    fn key(&mut self, key: u16) {
        match key {
            KEY_START => {
                self.running = true;
                self.counter = self.rl;
            }
            KEY_UNLOCK => self.unlocked = true,
            KEY_RELOAD => {
                self.counter = self.rl;
                self.unlocked = false;
            }
            _ => self.unlocked = false,
        }
    }
    fn set_prescaler(&mut self, pr: u8) {
        if self.unlocked {
            self.pr = pr;
        }
    }
    fn set_reload(&mut self, rl: u16) {
        if self.unlocked {
            self.rl = rl;
        }
    }
    fn busy(&mut self) -> bool {
        self.busy_polls = self.busy_polls.saturating_sub(1);
        self.busy_polls > 0
    }
}

/// What embassy-stm32 0.6's `IndependentWatchdog::new(500_000)` and
/// `unleash()` do to the registers (wdg/mod.rs): unlock, PR, RLR, start.
/// The start key on a running IWDG does not reload it.
fn embassy_new_and_unleash(w: &mut Iwdg, s: IwdgSetting) {
    w.key(KEY_UNLOCK);
    w.set_prescaler(s.pr);
    w.set_reload(s.rl);
    // KEY_START on a running watchdog: no reload (modelled explicitly)
    w.running = true;
}

#[test]
fn the_old_hand_over_left_125_ms_instead_of_500() {
    let s = IwdgSetting::for_timeout_us(500_000).unwrap();
    assert_eq!(s, IwdgSetting { pr: 0, rl: 3999 });
    let mut w = Iwdg::from_bootloader();
    assert_eq!(w.left_us(), 8_008_000);
    embassy_new_and_unleash(&mut w, s);
    assert_eq!(w.left_us(), 125_125, "issue 50 item 2");
}

#[test]
fn the_hand_over_reloads_the_full_new_timeout() {
    let s = IwdgSetting::for_timeout_us(500_000).unwrap();
    let mut w = Iwdg::from_bootloader();
    handover(&mut w, s).unwrap();
    assert_eq!((w.pr, w.rl), (0, 3999));
    assert_eq!(w.left_us(), 500_000);
    assert!(!w.unlocked, "the reload key locks the registers again");
    assert_eq!(s.timeout_us(), 500_000);
}

#[test]
fn a_stuck_update_is_reported_and_the_counter_still_reloaded() {
    let mut w = Iwdg::from_bootloader();
    w.busy_polls = u32::MAX;
    let r = handover(&mut w, IwdgSetting::for_timeout_us(500_000).unwrap());
    assert_eq!(r, Err(BootCtlError::WatchdogBusy));
    assert_eq!(w.counter, w.rl);
}

#[test]
fn watchdog_settings_cover_the_range() {
    assert_eq!(
        IwdgSetting::for_timeout_us(8_000_000).unwrap().timeout_us(),
        8_000_000
    );
    assert_eq!(IwdgSetting::BOOTLOADER.timeout_us(), 8_008_000);
    assert_eq!(
        IwdgSetting::for_timeout_us(0),
        Err(BootCtlError::WatchdogTimeout)
    );
    assert_eq!(
        IwdgSetting::for_timeout_us(40_000_000),
        Err(BootCtlError::WatchdogTimeout)
    );
}

/// FLASH_OPTR as the factory sets a dual-bank STM32G474RE (RM0440 §3.7.8,
/// 0xFFEF_F8AA; DBANK = 1, BFB2 = 0, RDP 0xAA).
const FACTORY_OPTR: u32 = 0xFFEF_F8AA;

#[test]
fn option_bytes_decide_the_boot_plan() {
    assert_eq!(check_option_bytes(FACTORY_OPTR), Ok(()));
    assert_eq!(boot_plan(FACTORY_OPTR), BootPlan::Update);
    let single = FACTORY_OPTR & !OPTR_DBANK;
    assert_eq!(
        boot_plan(single),
        BootPlan::StartOnly(BootCtlError::SingleBank)
    );
    let bfb2 = FACTORY_OPTR | OPTR_BFB2;
    assert_eq!(
        boot_plan(bfb2),
        BootPlan::StartOnly(BootCtlError::BootFromBank2)
    );
    let d = option_bytes_emcy_data(single);
    assert_eq!(d[0], 1);
    assert_eq!(d[1] & 0x40, 0, "DBANK bit of byte 2 clear");
    assert_eq!(d[3], 0xAA, "RDP level 0");
}

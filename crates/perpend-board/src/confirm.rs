//! When a freshly swapped-in image confirms itself (embassy-boot
//! `mark_booted`, issue 34 item 4, issue 50 item 3): only after it has come
//! up completely, i.e. a stored parameter record actually loaded (or none
//! was stored: nothing to reject), the CAN controller runs (a frame was
//! acknowledged on the bus) and the node has served the bus once (a
//! heartbeat sent, a SYNC answered, an NMT command or an SDO request of a
//! master handled). Until then a reset (panic, watchdog of a hung image,
//! power cut) makes the bootloader swap the old image back.
//!
//! [`BootConfirm`] collects the three conditions in any order and says
//! exactly once that it is time to confirm ([`BootConfirm::due`]); the
//! caller then calls `ProgramStore::mark_booted` ([`BootConfirm::run`]
//! does both). Confirming an image that is already confirmed writes
//! nothing (embassy-boot compares the magic first), so the firmware runs
//! it at every start.
//!
//! **Trial deadline** ([`TRIAL_DEADLINE_US`]): an image on trial that has
//! not confirmed itself [`TRIAL_DEADLINE_US`] after boot is done with
//! ([`BootConfirm::expired`]): the firmware resets and the bootloader
//! swaps the old image back. Before, an image whose frames were never
//! acknowledged still fed the watchdog and ran unconfirmed until the next
//! power cycle. A board that is not on trial never expires.
//!
//! **Storage**: a record that was found but rejected, or storage that
//! could not be read, never counts as loaded ([`storage_ok`]): an image
//! that cannot read the calibration the old one stored is reverted.
//!
//! Limits: "CAN running" is what the firmware reports (an acknowledged
//! transmission); a node alone on the bus, or on a bus whose master
//! never addresses it and with its heartbeat producer off (0x1017 = 0),
//! never confirms a new image and is reverted at the deadline, which is
//! the safe outcome.

use crate::program::{ProgramError, ProgramStore};
use crate::storage::Boot;

/// How long an image on trial may run unconfirmed after boot \[µs\]
/// (60 s: a master brings a node up well within it; the swap back takes
/// another ≈ 10 s).
pub const TRIAL_DEADLINE_US: u64 = 60_000_000;

/// Whether the parameter storage counts as loaded for the confirmation: a
/// stored record loaded, or nothing stored. A rejected record or an
/// unreadable storage does not.
pub fn storage_ok(boot: &Boot) -> bool {
    matches!(boot, Boot::Stored | Boot::Missing)
}

/// The confirmation conditions and whether the confirmation was made.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BootConfirm {
    storage: bool,
    can: bool,
    served: bool,
    done: bool,
    /// The running image is on trial (swapped in, not yet confirmed).
    trial: bool,
    /// The trial deadline was reported.
    expired: bool,
}

impl BootConfirm {
    /// Nothing seen yet.
    pub const fn new() -> Self {
        Self {
            storage: false,
            can: false,
            served: false,
            done: false,
            trial: false,
            expired: false,
        }
    }

    /// The running image is on trial (the bootloader's state says so).
    pub fn set_trial(&mut self, trial: bool) {
        self.trial = trial;
    }

    /// Whether the running image is on trial and not confirmed yet.
    pub fn on_trial(&self) -> bool {
        self.trial && !self.done
    }

    /// Whether the trial deadline has passed at `now_us` (µs since boot)
    /// without a confirmation: `true` once, then `false`. Never for an
    /// image that is not on trial.
    pub fn expired(&mut self, now_us: u64) -> bool {
        let e = self.on_trial() && !self.expired && now_us >= TRIAL_DEADLINE_US;
        self.expired |= e;
        e
    }

    /// The parameter storage was loaded (stored or factory parameters).
    pub fn storage_loaded(&mut self) {
        self.storage = true;
    }

    /// A frame was acknowledged on the bus.
    pub fn can_running(&mut self) {
        self.can = true;
    }

    /// A heartbeat was sent or a SYNC answered.
    pub fn served(&mut self) {
        self.served = true;
    }

    /// Whether every condition holds and the confirmation was not made
    /// yet; `true` once, then `false` for ever (also after the deadline
    /// expired: the image is being reverted).
    pub fn due(&mut self) -> bool {
        let due = self.storage && self.can && self.served && !self.done && !self.expired;
        self.done |= due;
        due
    }

    /// The confirmation was made (or attempted).
    pub fn done(&self) -> bool {
        self.done
    }

    /// Confirms the running image on `store` when [`Self::due`]: `None`
    /// when not due, else the result of `mark_booted`.
    pub fn run<P: ProgramStore>(&mut self, store: &mut P) -> Option<Result<(), ProgramError>> {
        self.due().then(|| store.mark_booted())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::image;
    use crate::program::{BootState, RamProgram};

    type Step = fn(&mut BootConfirm);
    const STEPS: [Step; 3] = [
        BootConfirm::storage_loaded,
        BootConfirm::can_running,
        BootConfirm::served,
    ];

    #[test]
    fn due_exactly_once_after_all_three_in_any_order() {
        for order in [
            [0, 1, 2],
            [0, 2, 1],
            [1, 0, 2],
            [1, 2, 0],
            [2, 0, 1],
            [2, 1, 0],
        ] {
            let mut c = BootConfirm::new();
            for (n, &i) in order.iter().enumerate() {
                assert!(!c.due(), "{order:?}: due after {n} conditions");
                STEPS[i](&mut c);
            }
            assert!(c.due(), "{order:?}");
            assert!(c.done());
            STEPS[order[2]](&mut c);
            assert!(!c.due(), "{order:?}: a second confirmation");
        }
    }

    /// A store whose active image v1 is confirmed and v2 was swapped in
    /// (on trial).
    fn on_trial() -> (RamProgram, Vec<u8>) {
        let mut s = RamProgram::new(8192);
        let v1 = image::sign(&[1; 300], 7, image::version(1, 0, 0), &image::TEST_SEED);
        s.active_image = v1.clone();
        s.image = image::sign(&[2; 400], 7, image::version(2, 0, 0), &image::TEST_SEED);
        s.mark_updated().unwrap();
        assert_eq!(s.reset(), BootState::Trial);
        (s, v1)
    }

    #[test]
    fn an_image_that_panics_at_start_is_reverted() {
        // The panic comes before the storage is loaded: nothing confirms,
        // panic-probe / HardFault / the watchdog reset the board.
        let (mut s, v1) = on_trial();
        let mut c = BootConfirm::new();
        assert_eq!(c.run(&mut s), None);
        assert_eq!(s.reset(), BootState::Boot);
        assert_eq!(s.active_image, v1, "the bootloader swapped v1 back");
    }

    #[test]
    fn an_image_that_hangs_after_can_start_is_reverted_by_the_watchdog() {
        // Storage and CAN came up, then the main loop hangs: no heartbeat,
        // no SYNC answered, the IWDG (500 ms) resets the board.
        let (mut s, v1) = on_trial();
        let mut c = BootConfirm::new();
        c.storage_loaded();
        c.can_running();
        assert_eq!(c.run(&mut s), None);
        assert_eq!(s.reset(), BootState::Boot);
        assert_eq!(s.active_image, v1);
    }

    #[test]
    fn an_image_on_trial_expires_once_at_the_deadline_and_a_confirmed_one_never() {
        let mut c = BootConfirm::new();
        c.set_trial(true);
        c.storage_loaded();
        assert!(!c.expired(TRIAL_DEADLINE_US - 1));
        assert!(c.expired(TRIAL_DEADLINE_US));
        assert!(!c.expired(TRIAL_DEADLINE_US + 1), "once");
        c.can_running();
        c.served();
        assert!(!c.due(), "no confirmation after the deadline");
        let mut ok = BootConfirm::new();
        ok.set_trial(true);
        ok.storage_loaded();
        ok.can_running();
        ok.served();
        assert!(ok.due());
        assert!(!ok.expired(10 * TRIAL_DEADLINE_US));
        let mut normal = BootConfirm::new();
        assert!(!normal.expired(10 * TRIAL_DEADLINE_US), "not on trial");
    }

    #[test]
    fn only_a_loaded_or_absent_record_counts_as_storage() {
        assert!(storage_ok(&Boot::Stored));
        assert!(storage_ok(&Boot::Missing));
        assert!(!storage_ok(&Boot::Rejected(perpend_core::Error::Decode(
            "x"
        ))));
        assert!(!storage_ok(&Boot::Unreadable(
            crate::storage::StoreError::Flash
        )));
    }

    #[test]
    fn an_image_that_comes_up_confirms_once_and_stays() {
        let (mut s, _) = on_trial();
        let v2 = s.active_image.clone();
        let mut c = BootConfirm::new();
        c.storage_loaded();
        c.served();
        c.can_running();
        assert_eq!(c.run(&mut s), Some(Ok(())));
        assert_eq!(c.run(&mut s), None);
        assert_eq!(s.reset(), BootState::Boot);
        assert_eq!(s.active_image, v2, "confirmed: no rollback");
    }
}

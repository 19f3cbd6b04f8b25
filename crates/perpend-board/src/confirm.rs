//! When a freshly swapped-in image confirms itself (embassy-boot
//! `mark_booted`, issue 34 item 4): only after it has come up completely,
//! i.e. the parameter storage was loaded, the CAN controller runs (a frame
//! was acknowledged on the bus) and the node has served the bus once (a
//! heartbeat sent or a SYNC answered). Until then a reset (panic, watchdog
//! of a hung image, power cut) makes the bootloader swap the old image
//! back.
//!
//! [`BootConfirm`] collects the three conditions in any order and says
//! exactly once that it is time to confirm ([`BootConfirm::due`]); the
//! caller then calls `ProgramStore::mark_booted` ([`BootConfirm::run`]
//! does both). Confirming an image that is already confirmed writes
//! nothing (embassy-boot compares the magic first), so the firmware runs
//! it at every start.
//!
//! Limits: "CAN running" is what the firmware reports (an acknowledged
//! transmission); a node alone on the bus never confirms a new image, and
//! the next reset reverts it, which is the safe outcome.

use crate::program::{ProgramError, ProgramStore};

/// The confirmation conditions and whether the confirmation was made.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct BootConfirm {
    storage: bool,
    can: bool,
    served: bool,
    done: bool,
}

impl BootConfirm {
    /// Nothing seen yet.
    pub const fn new() -> Self {
        Self {
            storage: false,
            can: false,
            served: false,
            done: false,
        }
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
    /// yet; `true` once, then `false` for ever.
    pub fn due(&mut self) -> bool {
        let due = self.storage && self.can && self.served && !self.done;
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

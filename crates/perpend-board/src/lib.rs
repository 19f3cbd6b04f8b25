//! Board logic (filled in by the firmware work).

//! # perpend-can
//!
//! The CANopen (CiA 301) device of the perpend sensor board: `no_std`, no
//! allocator, transport-agnostic. Frames in, frames out, time passed in as
//! microseconds (`u64`). The firmware feeds it from FDCAN; the host's
//! virtual board (`perpend board`) from slcan over TCP; the tests directly.
//!
//! ## Why not an existing stack
//!
//! Two `no_std` crates were read before writing this one:
//! `canopen-rs` 0.6 keeps the dictionary in a dynamic map of typed values
//! with static access rights only (no state- or lock-dependent writes, no
//! value ranges), has no 0x1010/0x1011, no SDO server timeout, and leaves
//! heartbeat and PDO timing to the application; `zencan-node` 0.0.5
//! generates the dictionary from TOML in a build script into global
//! statics, is MPL-2.0 (the workspace is MIT/Apache-2.0) and costs ~32 KB
//! flash. Both are pre-1.0. The subset the board needs (below) is small
//! enough that one table-driven implementation, whose every rule is ours to
//! test, is simpler to make fully correct than adapting either.
//!
//! ## Use
//!
//! ```
//! use perpend_can::{Defaults, Device, Frame, Measurement, NmtState};
//!
//! let mut dev = Device::new(0x10, &Defaults::nominal());
//! // dev.load_image(&stored)?;         // parameters from flash, if any
//! let mut sent = Vec::new();
//! dev.poll(0, &mut |f| sent.push(f));                 // boot-up 0x710 [00]
//! dev.handle(&Frame::new(0x000, &[0x01, 0x10]), 10, &mut |f| sent.push(f)); // NMT start
//! assert_eq!(dev.nmt_state(), NmtState::Operational);
//! dev.set_measurement(&Measurement::invalid(perpend_can::status::NO_PLANE));
//! dev.handle(&Frame::new(0x080, &[]), 20, &mut |f| sent.push(f));            // SYNC
//! assert_eq!(sent.len(), 1 + 4);                       // boot-up + 4 TPDOs
//! ```
//!
//! The application loop (`perpend_board::app::App` implements it for the
//! firmware and the virtual board):
//! 1. `Device::new(Params::factory().can.node_id, &Defaults::nominal())`
//!    (factory values: what 0x1011 restores), then `load_image` with the
//!    stored image (every persisted object) or `load_params` with a stored
//!    `perpend_core::params::Params`, if valid; then `poll` regularly
//!    (≤ 1 ms period) and `handle` every received frame;
//! 2. per sample: `publish` (= `set_measurement`, which increments 0x2007
//!    and triggers event-driven TPDOs, plus EMCY raised/cleared from the
//!    status word), or `set_measurement` with the application's own
//!    `signal_emcy` / `clear_emcy` policy;
//! 3. `take_events`: on [`Events::CONFIG_CHANGED`] re-read
//!    [`Device::calibration`], [`Device::transfer`], [`Device::acquisition`]
//!    (or `params(&current)`); on [`Events::RESET_COMM`] apply
//!    [`Device::communication`] (bit rate); on [`Events::REQUEST`] carry out
//!    [`Device::pending_request`] — for a [`Request::Store`] or
//!    [`Request::Restore`] write [`Device::persistent_image`] (it already
//!    holds what the request leaves stored: the saved group's current
//!    values, or the restored group's defaults, the rest as stored) and the
//!    record to flash — and call [`Device::finish_request`] with the outcome
//!    (the SDO confirmation is sent then).
//!
//! ## Public API summary
//!
//! * [`Frame`] `{ id: u16, rtr: bool, len: u8, data: [u8; 8] }`,
//!   `Frame::new(id, &payload)`, `payload()`.
//! * [`Device`]: `new(node_id, &Defaults)`, `handle(&Frame, now_us, out)`,
//!   `poll(now_us, out)` with `out: &mut impl FnMut(Frame)`;
//!   `nmt_state()`, `node_id()`, `take_events()`, `config_generation()`;
//!   `set_measurement(&Measurement)`, `publish(&Measurement)`,
//!   `measurement()`, `status()`,
//!   `sample_counter()`; `calibration(i)`, `transfer(i)`, `acquisition()`,
//!   `communication()`, `heartbeat_ms()`, `calibration_is_default()`,
//!   `read_u32/read_f32/read_str(index, sub)`;
//!   `signal_emcy(code, reg, mfr)`, `clear_emcy(code)`, `emcy_active(code)`,
//!   `error_register()`; `pending_request()`, `finish_request(ok, out)`,
//!   `persistent_image(&mut [u8; IMAGE_LEN])`, `load_image(&[u8])`;
//!   bridge to the stored record of `perpend_core::params`:
//!   `load_params(&Params)`, `params(&base) -> Params`.
//! * [`Defaults`] (`nominal()`, `from_params(&Params)`, `with_head(&Head4)`), [`Identity`],
//!   [`SensorCalibration`] (`to_sensor`, `from_sensor`), [`TransferFunction`],
//!   [`Acquisition`], [`Communication`], [`Measurement`] (`invalid`,
//!   `from_core`).
//! * LSS (CiA 305): [`lss`] (the slave's protocol state machine, COB-IDs,
//!   command specifiers, bit timing table 0); on the device
//!   `lss_unconfigured()`, `active_node_id()`, `lss_state()`,
//!   `take_bit_rate_switch()` (the application re-programs its controller),
//!   `set_pending_node_id(id)`; [`Request::StoreLss`].
//! * [`status`]: status-word bits and EMCY codes; [`od`]: the dictionary
//!   table and signatures; [`sdo::SdoAbort`]: abort codes; [`eds`]: the EDS
//!   writer.
//!
//! ## Behaviour (CiA 301 subset)
//!
//! * **NMT slave**: boot-up `0x700+id [00]` at the first `poll` after
//!   power-on or a reset; commands on COB-ID 0 (`[cs, node|0]`): start
//!   (0x01), stop (0x02), enter pre-operational (0x80), reset node (0x81:
//!   every object back to its power-on value, i.e. defaults overlaid with
//!   the last stored/loaded image; errors cleared), reset communication
//!   (0x82: 0x1000..0x1FFF parameters only). A node-id or bit rate written
//!   to 0x2400 becomes active at the next reset (communication or node),
//!   saved or not; TPDO COB-IDs that were the default for the old
//!   node-id follow it. Every state change clears the
//!   calibration unlock.
//! * **Heartbeat** `0x700+id [state]` every 0x1017 ms (0 = off): 0x7F
//!   pre-operational, 0x05 operational, 0x04 stopped.
//! * **SDO server** on 0x600+id → 0x580+id, pre-operational and operational
//!   only: expedited and segmented upload/download, toggle check, server
//!   timeout (`Defaults::sdo_timeout_us`, abort 0x05040000), block
//!   download with CRC (feature `sdo-block`, module `sdo::block`); block upload
//!   refused (0x05040001). See [`sdo`] for the codes. Order of checks:
//!   object (0x06020000) → sub-index (0x06090011) → access (0x06010002) →
//!   length (0x06070012 too long, 0x06070013 too short) → state (0x08000022) → lock (0x08000021) → value
//!   (0x06090030/31/32, PDO mapping 0x06040041/42/43).
//! * **Program download** (CiA 302-3, pre-operational): 0x1F50 sub 1
//!   program data (DOMAIN, write-only, streamed to the application as
//!   [`Request::ProgramData`] parts, data in [`Device::program_part`]),
//!   0x1F51 program control ([`Request::ProgramControl`]), 0x1F56
//!   identification and 0x1F57 flash status ([`Device::set_program_status`]).
//! * **SYNC** (COB-ID 0x80) in operational: TPDOs with transmission type
//!   1..240 are sent every n-th SYNC, type 0 at the SYNC after the mapped
//!   data changed.
//! * **TPDO 1..4** (0x1800+k / 0x1A00+k): COB-ID (bit 31 = not valid; bits
//!   0-30 and the inhibit time change only while not valid, else
//!   0x06090030; restricted ids refused), transmission type 0, 1..240, 254,
//!   255 (others 0x06090030); 254/255 are sent when the mapped data change
//!   (beyond the deadbands of 0x2009) and when the event timer (ms)
//!   expires, never within the inhibit time (100 µs); an empty mapping is
//!   never sent; mapping of up to 8 objects / 64 bits, changeable only
//!   while the PDO is not valid and (entries) while sub 0 is 0 (0x08000022
//!   otherwise).
//! * **EMCY** on 0x1014 (0x80+id): `[code lo, code hi, 0x1001, mfr[5]]`,
//!   at most one per inhibit time 0x1015 (100 µs); one per raise, one
//!   "error reset" (code 0, the remaining 0x1001, the cleared code in
//!   mfr 0-1) per clear; none in stopped and nothing queued before a stop
//!   after it; 0x1003 holds the last 8 distinct codes (a repeated code
//!   moves to sub 1; write 0 to sub 0 clears it).
//! * **LSS slave** (CiA 305, [`lss`]): 0x7E5 → 0x7E4; switch state global
//!   and selective, configure node-id (pending = 0x2400 sub 1, active at
//!   the next reset communication) and bit timing (1000/500/250/125
//!   kbit/s), activate bit timing (silent for twice the switch delay, the
//!   application switches the controller at [`Device::take_bit_rate_switch`]),
//!   store configuration ([`Request::StoreLss`]: 0x2400 only), inquire
//!   identity and node-id, identify (non-configured) remote slave,
//!   fastscan. A node started with node-id 0xFF is non-configured: it
//!   stays in initialisation, sends nothing and serves LSS only until it
//!   is given a node-id.
//! * **Store/restore** 0x1010/0x1011 sub 1 (all), 2 (0x1000..0x1FFF), 3
//!   (0x2000..) with "save" 0x65766173 / "load" 0x64616F6C (other values:
//!   0x08000020); read as 1 (on command). Persisted: 0x1015, 0x1017,
//!   0x1800..0x1803, 0x1A00..0x1A03, 0x2009, 0x2101..0x2105,
//!   0x2201..0x2204, 0x2300, 0x2310, 0x2400. "load" makes the group's defaults
//!   effective at the next reset node; 0x2400 (node-id, bit rate) is never
//!   restored.
//!
//! ## Object dictionary (manufacturer part; REAL32 unless noted)
//!
//! | index | sub | name | access |
//! |---|---|---|---|
//! | 0x2001 | 1..3 | surface normal x, y, z (unit, towards the head, TCS) | ro, PDO |
//! | 0x2002 | 1, 2, 3 | θ1, θ2, θ \[deg\] (Tian eq. 1-5) | ro, PDO |
//! | 0x2003 | 1, 2 | pitch, yaw \[deg\] (Chen eq. 22) | ro, PDO |
//! | 0x2004 | 1..4 | distances \[mm\] | ro, PDO |
//! | 0x2005 | 0 | status, UNSIGNED32 ([`status`]) | ro, PDO |
//! | 0x2006 | 0 | plane RMS residual \[mm\] | ro, PDO |
//! | 0x2007 | 0 | sample counter, UNSIGNED32 | ro, PDO |
//! | 0x2008 | 1, 2 | CAN transmit queue: frames dropped (queue full), peak fill; UNSIGNED32, since power-on | ro, PDO |
//! | 0x2010 | 0 | calibration unlock, UNSIGNED32: write "ucal" 0x6C616375 to unlock, 0 to lock; reads 1/0 | rw, pre-op |
//! | 0x2101..4 | 1..25 | sensor calibration: zero x,y,z \[mm\], direction x,y,z, d_ref \[mm\], gain, nl2, nl3, incidence \[mm\], crosstalk, thermal [mm/°C], temp_ref [°C], drift [mm/s]; 16..20 linearity table knots \[mm\] about d_ref, 21..23 its coefficients [mm⁻¹] (an active table needs strictly ascending knots, else 0x06090030); 24..25 spot bias cos φ, sin φ \[mm per unit tan²γ\] (\|·\| ≤ 10, else 0x06090031/32) | rw, pre-op + unlock |
//! | 0x2105 | 0 | the head's thermal time constant τ \[s\], 0..86400 (0 = no lag; below 0: 0x06090032, above: 0x06090031, NaN: 0x06090030): the thermal extension of every sensor is applied to the head temperature passed through a first-order lag of τ (`perpend_core::lag`) | rw, pre-op + unlock |
//! | 0x2201..4 | 1..4 | transfer function: kind U8 (0 = 4-20 mA shunt, 1 = 0-10 V divider), shunt \[Ω\] / divider ratio, mm at 4 mA / 0 V, mm at 20 mA / 10 V | rw, pre-op + unlock |
//! | 0x2300 | 1..4 | period \[µs\] U32 100..100000, oversampling U16 1..256 power of 2, method U8 (0 Chen, 1 LS), residual limit \[mm\]; period and oversampling together: oversampling × [`Defaults::adc_scan_ns`] ≤ period, else 0x06090030 | rw, pre-op |
//! | 0x2310 | 1..5 | surface model (issue 14): model U8 (0 plane, 1 sphere, 2 cylinder), signed radius \[mm\] REAL32 (10 ≤ \|R\| ≤ 100000, else 0x06090030 / 0x06090031 / 0x06090032), cylinder axis x, y, z REAL32 in −1..1 (not all zero with the cylinder selected: 0x06090030; set the axis before the model); applied per sample by the board | rw, pre-op |
//! | 0x2400 | 1, 2 | node-id U8 1..127, bit rate [kbit/s] U16 125/250/500/1000 | rw, pre-op |
//!
//! Default TPDOs, all transmission type 1 (every SYNC), 8 bytes each:
//!
//! | TPDO | COB-ID | content |
//! |---|---|---|
//! | 1 | 0x180+id | θ1, θ2 (0x2002 sub 1, 2) |
//! | 2 | 0x280+id | status (0x2005), sample counter (0x2007) |
//! | 3 | 0x380+id | normal x, y (0x2001 sub 1, 2) |
//! | 4 | 0x480+id | normal z (0x2001 sub 3), RMS residual (0x2006) |
//!
//! The sample counter in TPDO 2 lets the controller detect a stale sample;
//! the normal, angles and residual of a sample without a valid plane
//! (status bit 19) are 0 — never NaN; a zero normal is not a unit vector,
//! so it cannot be mistaken for a measurement.
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![deny(missing_docs)]

pub mod config;
pub mod device;
/// The EDS needs the objects' names (feature `names`).
#[cfg(feature = "names")]
pub mod eds;
pub mod error;
pub mod frame;
pub mod lss;
pub mod od;
pub mod sdo;
#[cfg(all(test, feature = "sdo-block"))]
mod sdo_block_tests;
pub mod status;

pub use config::{
    Acquisition, Communication, Defaults, Identity, Measurement, SensorCalibration, SurfaceModel,
    TransferFunction,
};
pub use device::{Device, Events, NmtState, Objects, Request, IMAGE_LEN};
pub use error::Error;
pub use frame::Frame;
pub use sdo::SdoAbort;

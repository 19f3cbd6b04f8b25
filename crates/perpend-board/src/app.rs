//! The application: the glue between the pipeline, the parameter storage
//! and the CANopen device (`perpend-can`). The firmware and the host's
//! virtual board drive the same [`App`]: frames in, frames out, time passed
//! in (µs), ADC samples in; no async, no HAL.
//!
//! ## Data flow
//!
//! * **boot** ([`App::new`]): the stored item is the [`Params`] record
//!   followed by the device's persistence image
//!   ([`perpend_can::Device::persistent_image`]: heartbeat, TPDO
//!   parameters, and the calibration/configuration objects). Both load or
//!   neither: a missing, rejected or unreadable item leaves the device on
//!   the factory defaults ([`Params::factory`] turned into
//!   [`perpend_can::Defaults`] by [`defaults_for`]); a rejected or
//!   unreadable one also raises EMCY 0x6300 (data set) until the next
//!   successful store.
//! * **sample** ([`App::on_sample`]): the die temperature goes through the
//!   head's thermal lag ([`crate::thermal`], τ from 0x2105) to the
//!   corrections and as it is to 0x200A; the pipeline's [`Output`] goes to
//!   0x2001..0x2007 (the device sends the TPDOs on SYNC or event) and its
//!   faults to EMCY (below).
//! * **configuration**: the object dictionary is the source of truth for
//!   everything it holds (0x2101..0x2104 calibration, 0x2105 thermal time
//!   constant, 0x2201..0x2204
//!   transfer functions, 0x2300 acquisition, 0x2310 surface model, 0x2400
//!   CAN); on every configuration change the pipeline's parameters and
//!   surface model are rebuilt from it ([`params_from_device`],
//!   `perpend_can::SurfaceModel::to_shape`). The surface model is not in
//!   the [`Params`] record: it is stored in the device image only (image
//!   layout 3; images of layouts 1 and 2 load with the plane model). Settings the dictionary does not hold (ADC
//!   reference, stuck and jump detectors, the live-zero signal span) come
//!   from the stored record. A combination that fails [`Params::validate`]
//!   sets status bit 21 and EMCY 0x6300; nothing invalid is ever stored.
//! * **store** (0x1010 "save"): the record (stamp + 1) and the image are
//!   stored as one item; the SDO confirmation follows the flash outcome.
//!   Sub 1 stores everything, sub 2 the communication objects
//!   (0x1000..0x1FFF), sub 3 the application objects (0x2000..); the
//!   other group keeps its stored values. **restore** (0x1011 "load",
//!   same sub-indices) stores a record with the group's defaults (sub 1
//!   and 3 also the record's settings without an object), active from the
//!   next reset node or power-on; the node-id and bit rate (0x2400) are
//!   never restored. A restore used to store a tombstone
//!   ([`crate::storage::TOMBSTONE`]); one written by older firmware still
//!   boots the factory defaults.
//!
//! ## EMCY
//!
//! The mapping of `perpend_can::Device::publish` (the codes are defined in
//! `perpend_can::status::emcy`), with hysteresis added:
//!
//! | condition (status word) | code | error register | data |
//! |---|---|---|---|
//! | sensor i open loop / overcurrent | 0x2111 + i | current | sensor 1..4, nibble |
//! | sensor i not valid otherwise (out of range, stuck, jumped) | 0xFF11 + i | manufacturer | sensor 1..4, nibble, stuck 0/1 |
//! | no valid plane (bit 19) | 0xFF02 | manufacturer | sensors used |
//! | configuration invalid (bit 21), boot record rejected | 0x6300 | generic | 0 |
//! | boot met unreadable (ECC) flash words ([`App::boot_read_faults`]) | 0x6300 | generic | 1, count (u32 LE) |
//! | store refused: supply below the PVD threshold | 0x3220 | voltage | 0 (raised and reset at once; SDO abort 0x08000020) |
//! | bus-off recovered ([`App::bus_off_recovered`]) | 0x8140 | communication | 0 |
//! | receive overrun ([`App::rx_overrun`]) | 0x8110 | communication | 0 |
//! | transmit queue full, frames dropped ([`App::tx_stats`]) | 0x8110 | communication | 1, dropped count (u32 LE) |
//!
//! A condition raises its EMCY on the first sample that shows it; it is
//! cleared only after [`EMCY_CLEAR_SAMPLES`] samples without it, so a
//! flickering fault does not flood the bus. Bus events are raised and
//! cleared at once (one EMCY, then its "error reset" with the register that
//! remains). The transmit-queue EMCY is sent when frames start being dropped
//! after [`TX_EMCY_QUIET_US`] without drops: once per congestion episode,
//! however long it lasts (0x2008 counts every frame).

use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;
use perpend_can::od::Group;
use perpend_can::status::{emcy, error_register};

use perpend_can::{
    Acquisition as OdAcquisition, Defaults, Device, Events, Frame, Measurement, Objects, Request,
    SensorCalibration, TransferFunction, IMAGE_LEN,
};
use perpend_core::normal::Method;
use perpend_core::params::{Bitrate, CanConfig, Frontend, Params, Transfer};
use perpend_core::Error;

use crate::pipeline::{Output, Pipeline, Sample};
use crate::status::{
    sensor_nibble, CONFIG_INVALID, NO_PLANE, SENSOR_OPEN_LOOP, SENSOR_OVERCURRENT, SENSOR_STUCK,
    SENSOR_VALID,
};
use crate::storage::{
    load_with_tail, save_with_tail, Boot, ParamStore, Recovery, SaveError, StoreError,
};

/// Samples without a condition before its EMCY is cleared (100 ms at
/// 1 kHz).
pub const EMCY_CLEAR_SAMPLES: u16 = 100;

/// Time without dropped transmit frames after which a new drop raises
/// EMCY 0x8110 again \[µs\].
pub const TX_EMCY_QUIET_US: u64 = 1_000_000;

/// OD code of the least-squares method in 0x2300 sub 3.
const OD_METHOD_CHEN: u8 = perpend_can::config::METHOD_CHEN;
const OD_METHOD_LS: u8 = perpend_can::config::METHOD_LEAST_SQUARES;

/// The device defaults for a parameter set (the factory defaults of the
/// board are `defaults_for(&Params::factory())`).
pub fn defaults_for(p: &Params) -> Defaults {
    let mut d = Defaults::nominal();
    d.calibration = core::array::from_fn(|i| SensorCalibration::from_sensor(&p.head.sensors[i]));
    d.transfer = core::array::from_fn(|i| transfer_to_od(&p.transfer[i]));
    d.acquisition = OdAcquisition {
        period_us: p.acq.period_us,
        oversampling: 1u16 << p.acq.os_log2.min(8),
        method: match p.acq.method {
            Method::Chen => OD_METHOD_CHEN,
            Method::LeastSquares => OD_METHOD_LS,
        },
        residual_limit_mm: p.acq.max_rms_mm,
    };
    d.bit_rate_kbps = (p.can.bitrate.bps() / 1000) as u16;
    d.adc_scan_ns = crate::scan::SCAN_NS;
    d
}

fn transfer_to_od(t: &Transfer) -> TransferFunction {
    let (kind, scale) = match t.frontend {
        Frontend::Shunt { ohm } => (perpend_can::config::TF_CURRENT_4_20MA, ohm),
        Frontend::Divider { ratio } => (perpend_can::config::TF_VOLTAGE_0_10V, ratio),
    };
    TransferFunction {
        kind,
        scale,
        mm_at_low: t.mm_lo,
        mm_at_high: t.mm_hi,
    }
}

fn transfer_from_od(t: &TransferFunction, extra: &Transfer) -> Result<Transfer, Error> {
    let (frontend, std_lo, std_hi) = match t.kind {
        perpend_can::config::TF_CURRENT_4_20MA => (Frontend::Shunt { ohm: t.scale }, 4.0, 20.0),
        perpend_can::config::TF_VOLTAGE_0_10V => (Frontend::Divider { ratio: t.scale }, 0.0, 10.0),
        _ => return Err(Error::OutOfRange("transfer kind")),
    };
    // The signal span is not in the dictionary: keep the stored one when
    // the front-end kind is unchanged, else the standard span of the kind.
    let same_kind = core::mem::discriminant(&frontend) == core::mem::discriminant(&extra.frontend);
    let (sig_lo, sig_hi) = if same_kind {
        (extra.sig_lo, extra.sig_hi)
    } else {
        (std_lo, std_hi)
    };
    Ok(Transfer {
        frontend,
        sig_lo,
        sig_hi,
        mm_lo: t.mm_at_low,
        mm_hi: t.mm_at_high,
    })
}

/// The pipeline parameters the object dictionary of `dev` describes, with
/// the settings it does not hold taken from `extra` (see the module docs).
///
/// # Errors
/// A zero-length beam direction or non-finite value
/// ([`perpend_core::Error`]), an unknown transfer kind, oversampling or bit
/// rate, a period shorter than one ADC scan at the oversampling
/// ([`crate::scan`]), or any error of [`Params::validate`].
pub fn params_from_device(dev: &Device, extra: &Params) -> Result<Params, Error> {
    params_from_objects(&dev.objects(), extra)
}

/// [`params_from_device`] of a set of objects (a device's, or those a
/// stored image would leave: [`Device::staged_objects`]).
///
/// # Errors
/// As [`params_from_device`].
pub fn params_from_objects(dev: &Objects<'_>, extra: &Params) -> Result<Params, Error> {
    let mut p = *extra;
    for i in 0..4 {
        let c = dev
            .calibration(i)
            .ok_or(Error::OutOfRange("sensor index"))?;
        p.head.sensors[i] = c.to_sensor::<f32>()?;
        let t = dev.transfer(i).ok_or(Error::OutOfRange("sensor index"))?;
        p.transfer[i] = transfer_from_od(&t, &extra.transfer[i])?;
    }
    let a = dev.acquisition();
    if !a.oversampling.is_power_of_two() || a.oversampling > 256 {
        return Err(Error::OutOfRange("oversampling ratio"));
    }
    if !crate::scan::fits(a.period_us, a.oversampling as u32) {
        return Err(Error::OutOfRange("sample period shorter than the ADC scan"));
    }
    let log2 = a.oversampling.trailing_zeros() as u8;
    p.acq.period_us = a.period_us;
    p.acq.os_log2 = log2;
    // Result width 12 + min(log2, 4) bits: as much resolution as 16 bits hold.
    p.acq.os_shift = log2.saturating_sub(4);
    p.acq.method = if a.method == OD_METHOD_CHEN {
        Method::Chen
    } else {
        Method::LeastSquares
    };
    p.acq.max_rms_mm = a.residual_limit_mm;
    p.thermal_tau_s = dev.thermal_tau_s();
    let c = dev.communication();
    p.can = CanConfig {
        // A non-configured node (LSS, 0xFF) keeps the record's last valid
        // node-id: the device image holds the 0xFF that wins at boot.
        node_id: if c.node_id == perpend_can::lss::UNCONFIGURED {
            dev.node_id()
        } else {
            c.node_id
        },
        bitrate: match c.bit_rate_kbps {
            1000 => Bitrate::M1,
            500 => Bitrate::K500,
            250 => Bitrate::K250,
            125 => Bitrate::K125,
            _ => return Err(Error::OutOfRange("bit rate")),
        },
    };
    p.validate()?;
    Ok(p)
}

/// The measurement objects for an output (NaN-free: see
/// [`crate::pipeline`]).
pub fn measurement_of(o: &Output) -> Measurement {
    Measurement {
        normal: o.normal,
        theta1_deg: o.theta1_deg,
        theta2_deg: o.theta2_deg,
        theta_deg: o.theta_deg,
        pitch_deg: o.pitch_deg,
        yaw_deg: o.yaw_deg,
        distances_mm: o.readings_mm,
        status: o.status,
        rms_mm: o.rms_mm,
    }
}

/// Number of EMCY conditions tracked: per sensor "current" and
/// "reading", no plane, data set.
const CONDS: usize = 10;

/// The EMCY conditions in `status` (the mapping of
/// `perpend_can::Device::publish`): `(code, error register, data if
/// active)`.
fn conditions(status: u32, boot_bad: bool) -> [(u16, u8, Option<[u8; 5]>); CONDS] {
    let stuck = u8::from(status & SENSOR_STUCK != 0);
    let mut out = [(0u16, 0u8, None); CONDS];
    let mut valid = 0u8;
    for i in 0..4 {
        let n = sensor_nibble(status, i);
        let current = n & (SENSOR_OPEN_LOOP | SENSOR_OVERCURRENT) != 0;
        let ok = n & SENSOR_VALID != 0;
        valid += u8::from(ok);
        out[2 * i] = (
            emcy::sensor_current(i),
            error_register::CURRENT,
            current.then_some([i as u8 + 1, n as u8, 0, 0, 0]),
        );
        out[2 * i + 1] = (
            emcy::sensor_reading(i),
            error_register::MANUFACTURER,
            (!current && !ok).then_some([i as u8 + 1, n as u8, stuck, 0, 0]),
        );
    }
    out[8] = (
        emcy::NO_PLANE,
        error_register::MANUFACTURER,
        (status & NO_PLANE != 0).then_some([valid, 0, 0, 0, 0]),
    );
    out[9] = (
        emcy::DATA_SET,
        error_register::GENERIC,
        (status & CONFIG_INVALID != 0 || boot_bad).then_some([0; 5]),
    );
    out
}

/// COB-ID of the SYNC (CiA 301 default, 0x1005).
const SYNC_COB_ID: u16 = 0x080;

/// The board application (see the module docs); `P` is the program store
/// of the field update ([`crate::program::BoardProgram`] unless the
/// firmware gives its DFU partition, [`App::with_program`]).
pub struct App<S: ParamStore, P: crate::program::ProgramStore = crate::program::BoardProgram> {
    dev: Device,
    pipe: Pipeline,
    store: S,
    extra: Params,
    boot: Boot,
    /// Unreadable flash words met at boot.
    read_faults: u32,
    /// Die temperature of the last sample, published at the next poll.
    temp_c: Option<f32>,
    /// The die temperature through the thermal time constant (0x2105).
    lag: crate::thermal::ThermalLag,
    /// 0x2500 = bootloader was written in pre-operational.
    bootloader: bool,
    /// Whether the bootloader lets the board into the ROM loader.
    rom_loader: crate::bootctl::RomLoaderPolicy,
    boot_bad: bool,
    /// The stored record: `extra` after the next reset node.
    next_extra: Params,
    cfg_gen: u32,
    quiet: [u16; CONDS],
    acq_changed: bool,
    can_changed: bool,
    last: Output,
    stores: u32,
    tx_dropped: u32,
    tx_last_drop_us: Option<u64>,
    /// A capture (0x2500) in progress.
    capture: Option<crate::capture::Capture>,
    /// A SYNC asked for a scan (SYNC-locked acquisition, 0x2301).
    sync_scan: bool,
    /// A communication error (bus-off) waits for its 0x1029 reaction.
    comm_error: bool,
    /// A store (0x1010/0x1011) waits for the storage's recovery
    /// ([`crate::storage::StoreError::Recovering`]): one page erase per
    /// poll, then the store and its SDO answer.
    recovering: bool,
    /// Acquisition was locked to SYNC at the last reload.
    locked: bool,
    /// CiA 302-3 program download (`program.rs`).
    program: P,
    program_state: crate::program::ProgramState,
    /// When a swapped-in image confirms itself (`confirm.rs`).
    confirm: crate::confirm::BootConfirm,
    /// 0x1F51 "start" marked the swap: the firmware resets into the
    /// bootloader.
    update_restart: bool,
}

/// Every field of [`App`]: a field added to it stops this from compiling
/// until [`App::init`] (which builds the app in place, field by field)
/// writes it too.
#[allow(dead_code)]
fn app_fields<S: ParamStore, P: crate::program::ProgramStore>(a: App<S, P>) {
    let App {
        dev: _,
        pipe: _,
        store: _,
        extra: _,
        boot: _,
        read_faults: _,
        temp_c: _,
        lag: _,
        bootloader: _,
        rom_loader: _,
        boot_bad: _,
        next_extra: _,
        cfg_gen: _,
        quiet: _,
        acq_changed: _,
        can_changed: _,
        last: _,
        stores: _,
        tx_dropped: _,
        tx_last_drop_us: _,
        capture: _,
        sync_scan: _,
        comm_error: _,
        recovering: _,
        locked: _,
        program: _,
        program_state: _,
        confirm: _,
        update_restart: _,
    } = a;
}

impl<S: ParamStore> App<S> {
    /// Boots with serial number 0 (tests; the firmware and the virtual
    /// board use [`App::with_serial`]).
    pub fn new(store: S) -> Self {
        Self::with_serial(store, 0)
    }

    /// [`App::with_program`] with this build's [`crate::program::BoardProgram`].
    pub fn with_serial(store: S, serial: u32) -> Self {
        App::with_program(store, serial, crate::program::board_program())
    }
}

impl<S: ParamStore, P: crate::program::ProgramStore> App<S, P> {
    /// Boots: loads the stored item from `store` (factory defaults if it is
    /// missing or bad) and builds the device, whose 0x1018 sub 4 is
    /// `serial` (the firmware passes [`perpend_can::config::serial_from_uid`]
    /// of the MCU's unique ID), and the pipeline; `program` is the store
    /// of the field update (0x1F50..0x1F57).
    pub fn with_program(store: S, serial: u32, program: P) -> Self {
        let mut slot = MaybeUninit::uninit();
        Self::init(&mut slot, store, serial, program);
        // SAFETY: `init` wrote every field.
        unsafe { slot.assume_init() }
    }

    /// [`App::with_program`] built in place in `slot` (the firmware's
    /// static): neither the app (≈ 11 KiB) nor its device (≈ 4.8 KiB)
    /// passes through a stack frame (issue 50 item 6). Returns the app.
    pub fn init(slot: &mut MaybeUninit<Self>, store: S, serial: u32, program: P) -> &mut Self {
        let app = Self::place(slot, store, serial, program);
        app.boot_load(serial);
        app
    }

    /// The factory state of [`App::init`], field by field. Not inlined:
    /// its temporaries (defaults, pipeline) leave the stack before the
    /// stored item is loaded.
    #[inline(never)]
    fn place(slot: &mut MaybeUninit<Self>, store: S, serial: u32, program: P) -> &mut Self {
        let factory = Params::factory();
        let a = slot.as_mut_ptr();
        // SAFETY: every field of `App` is written once through a raw
        // pointer into `slot` before `assume_init_mut`; the device is
        // built in place by `Device::init`. `app_fields` lists the fields
        // and stops compiling when one is added.
        unsafe {
            Device::init(
                &mut *addr_of_mut!((*a).dev).cast::<MaybeUninit<Device>>(),
                factory.can.node_id,
                &defaults_for(&factory).with_serial(serial),
            );
            addr_of_mut!((*a).pipe).write(Pipeline::new(factory, false));
            addr_of_mut!((*a).store).write(store);
            addr_of_mut!((*a).extra).write(factory);
            addr_of_mut!((*a).boot).write(Boot::Missing);
            addr_of_mut!((*a).read_faults).write(0);
            addr_of_mut!((*a).temp_c).write(None);
            addr_of_mut!((*a).lag).write(crate::thermal::ThermalLag::new());
            addr_of_mut!((*a).bootloader).write(false);
            addr_of_mut!((*a).rom_loader).write(crate::bootctl::RomLoaderPolicy {
                test_key: true,
                provisioned: false,
            });
            addr_of_mut!((*a).boot_bad).write(false);
            addr_of_mut!((*a).next_extra).write(factory);
            addr_of_mut!((*a).cfg_gen).write(0);
            addr_of_mut!((*a).quiet).write([0; CONDS]);
            addr_of_mut!((*a).acq_changed).write(false);
            addr_of_mut!((*a).can_changed).write(false);
            addr_of_mut!((*a).last).write(Output::default());
            addr_of_mut!((*a).stores).write(0);
            addr_of_mut!((*a).tx_dropped).write(0);
            addr_of_mut!((*a).tx_last_drop_us).write(None);
            addr_of_mut!((*a).capture).write(None);
            addr_of_mut!((*a).sync_scan).write(false);
            addr_of_mut!((*a).comm_error).write(false);
            addr_of_mut!((*a).recovering).write(false);
            addr_of_mut!((*a).locked).write(false);
            addr_of_mut!((*a).program).write(program);
            addr_of_mut!((*a).program_state).write(crate::program::ProgramState::default());
            addr_of_mut!((*a).confirm).write(crate::confirm::BootConfirm::new());
            addr_of_mut!((*a).update_restart).write(false);
            slot.assume_init_mut()
        }
    }

    /// Loads the stored item over the factory state [`App::init`] built
    /// (factory defaults if it is missing or bad), then the boot's
    /// confirmation, program and EMCY state.
    fn boot_load(&mut self, serial: u32) {
        let (boot, read_faults) = self.load_stored(serial);
        self.boot = boot;
        self.read_faults = read_faults;
        self.boot_bad = matches!(boot, Boot::Rejected(_) | Boot::Unreadable(_)) || read_faults > 0;
        self.cfg_gen = self.dev.config_generation();
        // Only a record that actually loaded (or none stored) counts: an
        // image that rejects the stored calibration is reverted.
        if crate::confirm::storage_ok(&self.boot) {
            self.confirm.storage_loaded();
        }
        let trial = self.program.on_trial();
        self.confirm.set_trial(trial);
        self.program_state = crate::program::ProgramState::of(&self.program);
        crate::program::publish(&self.program_state, &mut self.dev);
        self.reload();
        // Nothing to drain: the events of the boot itself are handled.
        self.dev.take_events();
        self.acq_changed = false;
        if self.boot_bad {
            let mut data = [0; 5];
            if read_faults > 0 {
                data[0] = 1;
                data[1..].copy_from_slice(&read_faults.to_le_bytes());
            }
            self.dev
                .signal_emcy(emcy::DATA_SET, error_register::GENERIC, data);
        }
    }

    /// The stored record and device image into `extra`, `next_extra` and
    /// the device (both or neither); returns where the boot parameters
    /// came from and the unreadable flash words met. Not inlined: its
    /// image buffer and record stay out of the caller's frame.
    #[inline(never)]
    fn load_stored(&mut self, serial: u32) -> (Boot, u32) {
        let mut image = [0u8; IMAGE_LEN];
        let (stored, mut boot, n) = load_with_tail(&mut self.store, &mut image);
        let read_faults = self.store.take_read_faults();
        if boot == Boot::Stored {
            match image.get(..n).map(|img| self.dev.load_image(img)) {
                Some(Ok(())) => {
                    self.extra = stored;
                    self.next_extra = stored;
                }
                _ => {
                    let factory = Params::factory();
                    let defaults = defaults_for(&factory).with_serial(serial);
                    self.dev.reinit(factory.can.node_id, &defaults);
                    boot = Boot::Rejected(Error::Decode("device image"));
                }
            }
        }
        (boot, read_faults)
    }

    /// Rebuilds the pipeline from the dictionary.
    fn reload(&mut self) {
        let calibrated = !self.dev.calibration_is_default();
        let old = *self.pipe.params();
        let shape = self.dev.surface().to_shape();
        match (params_from_device(&self.dev, &self.extra), shape) {
            (Ok(p), Ok(shape)) => {
                self.pipe.set_params(p, calibrated);
                self.pipe.set_shape(shape);
            }
            _ => self.pipe.invalidate(calibrated),
        }
        let new = self.pipe.params();
        let locked = self.dev.sync_locked();
        if new.acq.period_us != old.acq.period_us
            || new.acq.os_log2 != old.acq.os_log2
            || new.acq.os_shift != old.acq.os_shift
            || locked != self.locked
        {
            self.acq_changed = true;
        }
        self.locked = locked;
        self.cfg_gen = self.dev.config_generation();
    }

    /// Where the boot parameters came from.
    pub fn boot(&self) -> Boot {
        self.boot
    }

    /// Unreadable (ECC) flash double words met while loading at boot: the
    /// records holding them were skipped (EMCY 0x6300 `[1, count]`).
    pub fn boot_read_faults(&self) -> u32 {
        self.read_faults
    }

    /// The CANopen device.
    pub fn device(&self) -> &Device {
        &self.dev
    }

    /// The program store (the virtual board: reset, `mark_booted`).
    pub fn program_mut(&mut self) -> &mut P {
        &mut self.program
    }

    /// Replaces the program store (the virtual board's flash fake) and
    /// publishes its active image in 0x1F56.
    pub fn set_program(&mut self, program: P) {
        self.program = program;
        self.program_state = crate::program::ProgramState::of(&self.program);
        crate::program::publish(&self.program_state, &mut self.dev);
    }

    /// The CANopen device, mutable (tests, diagnostics).
    pub fn device_mut(&mut self) -> &mut Device {
        &mut self.dev
    }

    /// The pipeline.
    pub fn pipeline(&self) -> &Pipeline {
        &self.pipe
    }

    /// The storage (tests: inspect the fake flash).
    pub fn store_mut(&mut self) -> &mut S {
        &mut self.store
    }

    /// Gives the storage back (a simulated reboot builds a new `App` on it).
    pub fn into_store(self) -> S {
        self.store
    }

    /// The last output.
    pub fn last_output(&self) -> &Output {
        &self.last
    }

    /// Number of successful stores since boot.
    pub fn stores(&self) -> u32 {
        self.stores
    }

    /// The CAN settings to run the controller with: the active node-id and
    /// the configured bit rate (0x2400, effective after a reset).
    pub fn can_config(&self) -> CanConfig {
        let bitrate = match self.dev.communication().bit_rate_kbps {
            500 => Bitrate::K500,
            250 => Bitrate::K250,
            125 => Bitrate::K125,
            _ => Bitrate::M1,
        };
        CanConfig {
            node_id: self.dev.node_id(),
            bitrate,
        }
    }

    /// The acquisition settings the ADC and its timer must use.
    pub fn acquisition(&self) -> perpend_core::params::Acquisition {
        self.pipe.params().acq
    }

    /// `Some(settings)` once after the acquisition period, oversampling or
    /// the SYNC lock ([`App::sync_locked`]) changed: the firmware
    /// reprograms the timer and the ADC.
    pub fn take_acq_change(&mut self) -> Option<perpend_core::params::Acquisition> {
        core::mem::take(&mut self.acq_changed).then(|| self.acquisition())
    }

    /// `Some(settings)` once after an NMT reset (node or communication):
    /// the firmware re-initialises the CAN controller with them. (An LSS
    /// bit-rate switch comes from `device_mut().take_bit_rate_switch()`.)
    pub fn take_can_change(&mut self) -> Option<CanConfig> {
        core::mem::take(&mut self.can_changed).then(|| self.can_config())
    }

    /// Handles a received frame.
    pub fn handle(&mut self, frame: &Frame, now_us: u64, out: &mut impl FnMut(Frame)) {
        self.dev.handle(frame, now_us, out);
        // A SYNC served in operational (its TPDOs), an NMT command or an
        // SDO request of a master serves the bus (`confirm.rs`); checked
        // without wrapping `out`, which would cost the SYNC path some 40
        // instructions (`cargo xtask mcu-bench`).
        if !self.confirm.done() && self.serves(frame) {
            self.confirm.served();
        }
        self.service(out);
    }

    /// Whether handling `frame` served a master (`confirm.rs`): a SYNC in
    /// operational, an NMT command for this node (or all), an SDO request
    /// to this node. Works when the master consumes no heartbeat (0x1017
    /// = 0) and sends no SYNC.
    fn serves(&self, frame: &Frame) -> bool {
        let node = self.dev.node_id();
        match frame.id {
            SYNC_COB_ID => self.dev.nmt_state() == perpend_can::NmtState::Operational,
            0x000 => frame.len == 2 && (frame.data[1] == 0 || frame.data[1] == node),
            id => id == 0x600 + u16::from(node),
        }
    }

    /// Whether the image on trial has run [`crate::confirm::TRIAL_DEADLINE_US`]
    /// since boot without confirming itself: `true` once; the firmware
    /// then resets and the bootloader swaps the old image back. Never
    /// for an image that is not on trial. Call it every tick.
    pub fn trial_expired(&mut self, now_us: u64) -> bool {
        self.confirm.expired(now_us)
    }

    /// Whether the running image is on trial and not yet confirmed.
    pub fn on_trial(&self) -> bool {
        self.confirm.on_trial()
    }

    /// What the bootloader allows for 0x2500 = bootloader
    /// ([`crate::bootctl::BootInfo::policy`]; the host's default allows
    /// it, as a test-key build). Refused: the SDO write aborts with
    /// 0x08000022 and nothing resets.
    pub fn set_rom_loader_policy(&mut self, policy: crate::bootctl::RomLoaderPolicy) {
        self.rom_loader = policy;
        self.dev.set_rom_loader_allowed(policy.allows());
    }

    /// The ROM-loader policy in force.
    pub fn rom_loader_policy(&self) -> crate::bootctl::RomLoaderPolicy {
        self.rom_loader
    }

    /// Reports option bytes that do not give the flash layout
    /// ([`crate::bootctl::check_option_bytes`]): EMCY
    /// [`crate::bootctl::EMCY_OPTION_BYTES`], kept active (the board
    /// writes no flash until they are fixed). Nothing for right ones.
    pub fn report_option_bytes(&mut self, optr: u32) {
        if crate::bootctl::check_option_bytes(optr).is_err() {
            self.dev.signal_emcy(
                crate::bootctl::EMCY_OPTION_BYTES,
                error_register::GENERIC,
                crate::bootctl::option_bytes_emcy_data(optr),
            );
        }
    }

    /// Whether 0x1F51 "start" has marked a verified image for the swap
    /// (once): the firmware then sends the SDO answer and resets into the
    /// bootloader, which swaps the image in.
    pub fn take_update_restart(&mut self) -> bool {
        core::mem::take(&mut self.update_restart)
    }

    /// Confirms a freshly swapped-in image (`ProgramStore::mark_booted`)
    /// once it has come up completely (`confirm.rs`): the storage was
    /// loaded (at boot), `can_running` (the firmware saw a frame
    /// acknowledged on the bus) and a heartbeat was sent or a SYNC
    /// answered. `Some(result)` once, when it confirmed; call it every tick.
    pub fn confirm_boot(
        &mut self,
        can_running: bool,
    ) -> Option<Result<(), crate::program::ProgramError>> {
        if can_running {
            self.confirm.can_running();
        }
        self.confirm.run(&mut self.program)
    }

    /// Runs the device's timers (heartbeat, event timers, SDO timeout,
    /// queued EMCY); call at least every millisecond.
    pub fn poll(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        if core::mem::take(&mut self.comm_error) {
            self.dev.communication_error(now_us, out);
        }
        // A heartbeat sent serves the bus (`confirm.rs`); the boot-up
        // message (same COB-ID, state byte 0) does not. Counted by the
        // device, not by wrapping `out`: a second closure type would be a
        // second copy of every send path below `poll` (≈ 1.2 KB of flash).
        let beats = self.dev.heartbeats_sent();
        self.dev.poll(now_us, out);
        if !self.confirm.done() && self.dev.heartbeats_sent() != beats {
            self.confirm.served();
        }
        if self.recovering {
            self.recover_step(out);
        }
        if let Some(t) = self.temp_c.take() {
            self.dev.set_die_temperature(t);
        }
        self.service(out);
    }

    /// Whether 0x2500 = [`perpend_can::od::CMD_BOOTLOADER`] was written in
    /// pre-operational since the last call: the firmware then resets into
    /// the system bootloader (docs/bring-up.md, field update).
    pub fn take_bootloader_request(&mut self) -> bool {
        core::mem::take(&mut self.bootloader)
    }

    /// Reports the reset cause read at boot: 0x200B sub 1 = the RCC_CSR
    /// flags; after a watchdog reset EMCY 0x6010 `[flags, 0, 0, 0, 0]`
    /// (raised and reset at once).
    pub fn report_reset(&mut self, flags: crate::health::ResetFlags) {
        self.dev.set_board_health(1, u32::from(flags.0));
        if flags.is_watchdog() {
            let code = crate::health::EMCY_WATCHDOG_RESET;
            self.dev
                .signal_emcy(code, error_register::GENERIC, [flags.0, 0, 0, 0, 0]);
            self.dev.clear_emcy(code);
        }
    }

    /// Publishes the firmware's health figures in 0x200B: worst main-loop
    /// time [cycles] (sub 2), stack used [bytes] (sub 3), VREF+ [mV]
    /// (sub 4, 0 = not measured).
    pub fn set_health(&mut self, worst_loop_cycles: u32, stack_used: u32, vref_mv: u32) {
        self.dev.set_board_health(2, worst_loop_cycles);
        self.dev.set_board_health(3, stack_used);
        self.dev.set_board_health(4, vref_mv);
    }

    /// Whether acquisition is locked to SYNC (0x2301 sub 1): the firmware
    /// and the virtual board then scan once per [`App::take_sync_scan`]
    /// instead of on their timer.
    pub fn sync_locked(&self) -> bool {
        self.dev.sync_locked()
    }

    /// Whether a SYNC asked for a scan since the last call (SYNC-locked
    /// acquisition): start one now and pass it to [`App::on_sample`] with
    /// the time it was started.
    pub fn take_sync_scan(&mut self) -> bool {
        core::mem::take(&mut self.sync_scan)
    }

    /// Processes one ADC scan taken at `now_us`; publishes it to the
    /// dictionary and updates the EMCY state. No time reaches the
    /// corrections: drift is a nuisance of the calibration run, folded into
    /// the zero points at its end and never extrapolated (issue 11 item 8,
    /// `perpend_formats::paramfile::SensorParams::fold_drift`); a stored drift
    /// coefficient is not applied. The corrections get the die temperature
    /// through the head's thermal time constant (0x2105,
    /// [`crate::thermal::ThermalLag`], stepped on `now_us`; τ = 0: the
    /// reading as it is); 0x200A publishes the reading itself.
    pub fn on_sample(&mut self, sample: &Sample, now_us: u64) -> Output {
        let tau = self.pipe.params().thermal_tau_s;
        let s = Sample {
            t_s: None,
            temp_c: self.lag.update(sample.temp_c, now_us, tau),
            ..*sample
        };
        let o = self.pipe.process(&s);
        self.temp_c = sample.temp_c;
        self.dev.set_sample_time(now_us);
        self.dev.set_measurement(&measurement_of(&o));
        self.update_emcy(o.status);
        if let Some(done) = self.capture.as_mut().and_then(|c| c.add(&o)) {
            self.capture = None;
            self.dev.finish_capture(done.angles_deg, done.used);
        }
        self.last = o;
        o
    }

    /// The CAN controller recovered from bus-off: EMCY 0x8140, and the
    /// communication-error reaction of 0x1029 at the next poll.
    pub fn bus_off_recovered(&mut self) {
        self.pulse(emcy::BUS_OFF_RECOVERED);
        self.comm_error = true;
    }

    /// Received frames were lost: EMCY 0x8110.
    pub fn rx_overrun(&mut self) {
        self.pulse(emcy::CAN_OVERRUN);
    }

    /// The transmit queue's counters ([`crate::txq::TxStats`]) at
    /// `now_us`: published in 0x2008; frames dropped after
    /// [`TX_EMCY_QUIET_US`] without drops raise EMCY 0x8110 with data
    /// `[1, dropped LE]` (raised and cleared at once, like the bus events).
    /// Call it after every [`crate::txq::TxQueue::service`].
    pub fn tx_stats(&mut self, s: crate::txq::TxStats, now_us: u64) {
        self.dev.set_tx_counters(s.dropped, s.peak as u32);
        if s.dropped == self.tx_dropped {
            return;
        }
        self.tx_dropped = s.dropped;
        let quiet = self
            .tx_last_drop_us
            .is_none_or(|t| now_us.saturating_sub(t) >= TX_EMCY_QUIET_US);
        self.tx_last_drop_us = Some(now_us);
        if quiet {
            let d = s.dropped.to_le_bytes();
            self.pulse_with(emcy::CAN_OVERRUN, [1, d[0], d[1], d[2], d[3]]);
        }
    }

    fn pulse(&mut self, code: u16) {
        self.pulse_with(code, [0; 5]);
    }

    fn pulse_with(&mut self, code: u16, data: [u8; 5]) {
        self.dev
            .signal_emcy(code, error_register::COMMUNICATION, data);
        self.dev.clear_emcy(code);
    }

    fn update_emcy(&mut self, status: u32) {
        // The usual sample (issue 50 item 8: ≈ 150 instructions): no
        // condition holds and no EMCY is active, so nothing is raised,
        // cleared or counted.
        let sensors_ok = (0..4).all(|i| {
            let n = sensor_nibble(status, i);
            n & (SENSOR_OPEN_LOOP | SENSOR_OVERCURRENT) == 0 && n & SENSOR_VALID != 0
        });
        if sensors_ok
            && status & (NO_PLANE | CONFIG_INVALID) == 0
            && !self.boot_bad
            && !self.dev.any_emcy_active()
        {
            return;
        }
        // by reference: iterating the array by value copied all of it
        // (100 B, about 100 instructions per sample)
        let conds = conditions(status, self.boot_bad);
        for (k, &(code, reg, data)) in conds.iter().enumerate() {
            match data {
                Some(data) => {
                    self.quiet[k] = 0;
                    if !self.dev.emcy_active(code) {
                        self.dev.signal_emcy(code, reg, data);
                    }
                }
                None => {
                    if self.dev.emcy_active(code) {
                        self.quiet[k] = self.quiet[k].saturating_add(1);
                        if self.quiet[k] >= EMCY_CLEAR_SAMPLES {
                            self.dev.clear_emcy(code);
                            self.quiet[k] = 0;
                        }
                    }
                }
            }
        }
    }

    fn service(&mut self, out: &mut impl FnMut(Frame)) {
        let ev = self.dev.take_events();
        if ev.contains(Events::SYNC_SAMPLE) {
            self.sync_scan = true;
        }
        if ev.contains(Events::COMMAND) {
            self.capture = (self.dev.command() == perpend_can::od::CMD_CAPTURE)
                .then(|| crate::capture::Capture::new(self.dev.capture_samples()));
            self.bootloader = self.dev.command() == perpend_can::od::CMD_BOOTLOADER
                && self.dev.nmt_state() == perpend_can::NmtState::PreOperational
                && self.rom_loader.allows();
        }
        if ev.contains(Events::REQUEST) {
            if let Some(req) = self.dev.pending_request() {
                let (store, state) = (&mut self.program, &mut self.program_state);
                let started = state.running;
                let ok = crate::program::serve(store, state, &mut self.dev, req)
                    .unwrap_or_else(|| self.store_now(req));
                self.update_restart |= !started && self.program_state.running;
                // NoRequest cannot happen: a request is pending.
                if !self.recovering {
                    let _ = self.dev.finish_request(ok, out);
                }
            }
        }
        if ev.contains(Events::RESET_NODE) {
            crate::program::publish(&self.program_state, &mut self.dev);
            // The stored record's settings without an object (ADC
            // reference, detectors, signal spans) apply from now on too.
            self.extra = self.next_extra;
        }
        if ev.contains(Events::CONFIG_CHANGED)
            || ev.contains(Events::RESET_NODE)
            || self.dev.config_generation() != self.cfg_gen
        {
            self.reload();
        }
        if ev.contains(Events::RESET_NODE) || ev.contains(Events::RESET_COMM) {
            self.can_changed = true;
        }
    }

    /// Carries out a store or restore: stores the record and the image the
    /// request leaves (both describe the same values: the record is taken
    /// from a copy of the device with the image loaded); true on success.
    /// A restore of the application parameters also restores the record's
    /// settings without an object to the factory ones.
    fn store_now(&mut self, req: Request) -> bool {
        let mut image = [0u8; IMAGE_LEN];
        self.dev.persistent_image(&mut image);
        let base = match req {
            Request::Restore(Group::All | Group::Application) => Params::factory(),
            _ => self.next_extra,
        };
        let Some(mut p) = staged_params(&self.dev, &image, &base) else {
            return false;
        };
        p.stamp = self.extra.stamp.wrapping_add(1).max(1);
        match save_with_tail(&mut self.store, &p, &image) {
            Ok(()) => {
                self.extra.stamp = p.stamp;
                self.next_extra = p;
                self.stores += 1;
                if self.boot_bad {
                    self.boot_bad = false;
                }
                true
            }
            Err(SaveError::Store(StoreError::LowSupply)) => {
                self.dev
                    .signal_emcy(EMCY_LOW_SUPPLY, error_register::VOLTAGE, [0; 5]);
                self.dev.clear_emcy(EMCY_LOW_SUPPLY);
                false
            }
            Err(SaveError::Store(StoreError::Recovering)) => {
                self.recovering = true;
                false
            }
            Err(_) => false,
        }
    }

    /// One step of the storage's recovery; when it ends, the pending store
    /// is carried out and answered.
    fn recover_step(&mut self, out: &mut impl FnMut(Frame)) {
        let ok = match self.store.recovery_step() {
            Recovery::Running => return,
            Recovery::Failed(_) => false,
            Recovery::Done | Recovery::Idle => {
                self.recovering = false;
                match self.dev.pending_request() {
                    Some(req) => self.store_now(req),
                    None => return,
                }
            }
        };
        self.recovering = false;
        let _ = self.dev.finish_request(ok, out);
    }
}

/// The record a store writes: the parameters of the objects `dev` would
/// hold with `image` loaded ([`Device::staged_objects`]: their values,
/// ≈ 1.4 KiB, not a copy of the device, ≈ 4.8 KiB), the settings without
/// an object from `base`. Not inlined: the values stay in this frame,
/// apart from the store's item buffer (one frame held a device copy and
/// the buffer, 9,304 B, more than the 8 KiB stack guard: issue 50 item 6).
#[inline(never)]
fn staged_params(dev: &Device, image: &[u8; IMAGE_LEN], base: &Params) -> Option<Params> {
    let mut values = [0u32; perpend_can::od::ENTRIES];
    let staged = dev.staged_objects(image, &mut values).ok()?;
    params_from_objects(&staged, base).ok()
}

/// EMCY code of a store refused for low supply voltage (CiA 301 0x3220
/// "input voltage too low").
pub const EMCY_LOW_SUPPLY: u16 = 0x3220;

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
#[path = "app_tests.rs"]
mod tests;

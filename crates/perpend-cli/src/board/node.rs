//! The virtual board without its transport: the firmware's application
//! ([`perpend_board::app::App`]: pipeline, CANopen device, parameter
//! storage on an in-memory flash) fed by the simulated head, driven by the
//! caller's clock. The TCP/slcan server and the tests drive this.
//!
//! Start-up: when the board must differ from the factory state (another
//! node-id, a head from `--sensors`, a calibration from `--params`), a
//! record is written to the in-memory flash first, exactly as a store
//! (0x1010) would write it, and the application boots from it. So the
//! node-id, head and calibration given on the command line are the stored
//! state: they survive NMT resets; 0x1011 "load" followed by a reset node
//! brings the firmware's factory state back (node-id 0x20, nominal head).
//!
//! Transmit: as on the board, every frame the application produces goes
//! through the software queue ([`perpend_board::txq::TxQueue`]) into a
//! controller with three transmit slots ([`VirtualCan`]); the virtual bus
//! sends them at once (no bus time), lowest identifier first, unless a
//! "no acknowledge" fault is active ([`VirtualBoard::set_bus_noack`]):
//! then the slots stay full, the queue fills and counts what it drops
//! (0x2008, EMCY 0x8110), and acquisition and SDO handling go on.
//!
//! Bit rate: the board's controller runs at the rate of 0x2400 sub 2 as of
//! the last NMT reset or LSS bit-rate switch ([`VirtualBoard::bit_rate_kbps`]);
//! the server passes a frame between the board and a client or another
//! board only when their rates agree (a client that never set one hears
//! every rate).
//!
//! Limits: no temperature input.

use anyhow::{anyhow, Result};
use perpend_board::app::{defaults_for, App};
use perpend_board::pipeline::{Output, Sample};
use perpend_board::program::{BootState, ProgramStore};
use perpend_board::storage::{host_store, save_with_tail, HostFlash};
use perpend_board::txq::{TryWrite, TxController, TxQueue, TX_QUEUE_LEN};
use perpend_can::lss::UNCONFIGURED;
use perpend_can::{Device, Frame, IMAGE_LEN};
use perpend_core::head::Head4;
use perpend_core::params::Params;

use super::sim::SimHead;

pub use super::update::HostApp;

/// What the board starts with.
#[derive(Debug, Clone)]
pub struct BoardConfig {
    /// Node-id 1..=127, or 0xFF ([`UNCONFIGURED`]): the board waits for
    /// LSS (CiA 305).
    pub node_id: u8,
    /// Head the board is built with (its stored geometry), if not the
    /// factory head.
    pub head: Option<Head4<f64>>,
    /// Calibrated head (stored calibration), if any; also the simulated
    /// truth.
    pub calibration: Option<Head4<f64>>,
    /// The head's thermal time constant \[s\] stored with it (0x2105;
    /// 0 = no lag).
    pub thermal_tau_s: f64,
}

/// The stored record the board starts from, or `None` for a factory board.
/// Node-id [`UNCONFIGURED`] (0xFF): the record keeps the factory node-id,
/// the device image the 0xFF of a node that waits for LSS (CiA 305), as
/// LSS "configure node-id 0xFF" + "store configuration" would leave it.
fn seed_record(cfg: &BoardConfig) -> Result<Option<(Params, [u8; IMAGE_LEN])>> {
    let factory = Params::factory();
    if cfg.node_id == factory.can.node_id
        && cfg.head.is_none()
        && cfg.calibration.is_none()
        && cfg.thermal_tau_s == 0.0
    {
        return Ok(None);
    }
    let unconfigured = cfg.node_id == UNCONFIGURED;
    let mut p = factory;
    if !unconfigured {
        p.can.node_id = cfg.node_id;
    }
    if let Some(h) = cfg.calibration.as_ref().or(cfg.head.as_ref()) {
        p.head = h.cast();
        p.validate()
            .map_err(|e| anyhow!("the head cannot be stored on the board: {e}"))?;
    }
    p.thermal_tau_s = cfg.thermal_tau_s as f32;
    p.validate()
        .map_err(|e| anyhow!("the thermal time constant cannot be stored on the board: {e}"))?;
    p.stamp = 1;
    let mut dev = Device::new(p.can.node_id, &defaults_for(&p));
    dev.load_params(&p)
        .map_err(|e| anyhow!("the head does not fit the object dictionary: {e}"))?;
    if unconfigured {
        dev.set_pending_node_id(UNCONFIGURED);
    }
    let mut img = [0u8; IMAGE_LEN];
    dev.persistent_image(&mut img);
    Ok(Some((p, img)))
}

/// The serial number of a virtual board run with `--seed seed`: the
/// firmware's fold of a 96-bit unique ID
/// ([`perpend_can::config::serial_from_uid`]) applied to "virt" followed by
/// the seed's 8 little-endian bytes.
pub fn serial_for_seed(seed: u64) -> u32 {
    let mut uid = [0u8; 12];
    uid[..4].copy_from_slice(b"virt");
    uid[4..].copy_from_slice(&seed.to_le_bytes());
    perpend_can::config::serial_from_uid(&uid)
}

/// The virtual CAN controller: three transmit slots, like the FDCAN.
#[derive(Debug, Default)]
pub struct VirtualCan {
    slots: Vec<Frame>,
    noack_until_us: Option<u64>,
}

impl VirtualCan {
    /// Transmit slots.
    pub const SLOTS: usize = 3;

    /// Whether the bus acknowledges at `now_us`.
    pub fn acked(&self, now_us: u64) -> bool {
        self.noack_until_us.is_none_or(|t| now_us >= t)
    }

    /// Sends the pending frames to `out` (lowest identifier first, equal
    /// identifiers in write order) if the bus acknowledges; returns how
    /// many.
    fn transmit(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) -> usize {
        if !self.acked(now_us) {
            return 0;
        }
        self.slots.sort_by_key(|f| f.id);
        let n = self.slots.len();
        self.slots.drain(..).for_each(&mut *out);
        n
    }
}

impl TxController for VirtualCan {
    fn try_write(&mut self, f: &Frame) -> TryWrite {
        if self.slots.len() < Self::SLOTS {
            self.slots.push(*f);
            TryWrite::Accepted
        } else {
            TryWrite::Full
        }
    }
}

/// The virtual board.
pub struct VirtualBoard {
    app: HostApp,
    sim: SimHead,
    txq: TxQueue<TX_QUEUE_LEN>,
    can: VirtualCan,
    /// The bit rate its controller runs at \[kbit/s\].
    kbps: u16,
    /// Serial number (0x1018 sub 4), kept over a restart.
    serial: u32,
    /// A new image confirms itself (`--fault update:no-confirm`: no).
    confirms: bool,
    /// A new image hangs until then (board time \[µs\]), then the
    /// watchdog resets the board ([`super::update`]).
    hung_until: Option<u64>,
}

impl VirtualBoard {
    /// Boots a board with `cfg` whose head looks through `sim`, with the
    /// serial number of seed 1 ([`serial_for_seed`]).
    ///
    /// # Errors
    /// A head or node-id the board cannot store.
    pub fn new(cfg: &BoardConfig, sim: SimHead) -> Result<Self> {
        Self::with_serial(cfg, sim, serial_for_seed(1))
    }

    /// Boots a board like [`VirtualBoard::new`] whose 0x1018 sub 4 is
    /// `serial`.
    ///
    /// # Errors
    /// A head or node-id the board cannot store.
    pub fn with_serial(cfg: &BoardConfig, sim: SimHead, serial: u32) -> Result<Self> {
        if !((1..=127).contains(&cfg.node_id) || cfg.node_id == UNCONFIGURED) {
            return Err(anyhow!("--node-id {}: must be 1..127 or 0xFF", cfg.node_id));
        }
        let mut store = host_store(HostFlash::new());
        if let Some((p, img)) = seed_record(cfg)? {
            save_with_tail(&mut store, &p, &img)
                .map_err(|e| anyhow!("writing the start-up record: {e:?}"))?;
        }
        let mut app = App::with_serial(store, serial);
        let product = app.device().defaults().identity.product_code;
        app.set_program(super::update::factory_program(product));
        let kbps = (app.can_config().bitrate.bps() / 1000) as u16;
        Ok(Self {
            app,
            sim,
            txq: TxQueue::new(),
            can: VirtualCan::default(),
            kbps,
            serial,
            confirms: true,
            hung_until: None,
        })
    }

    /// The application (device, pipeline, storage).
    pub fn app(&self) -> &HostApp {
        &self.app
    }

    /// The application, mutable.
    pub fn app_mut(&mut self) -> &mut HostApp {
        &mut self.app
    }

    /// The simulated head, mutable (inject faults).
    pub fn sim_mut(&mut self) -> &mut SimHead {
        &mut self.sim
    }

    /// The bit rate the board's CAN controller runs at \[kbit/s\]: the
    /// configured one (0x2400 sub 2) from the last NMT reset or LSS
    /// bit-rate switch on, as the firmware re-programs the FDCAN.
    pub fn bit_rate_kbps(&self) -> u16 {
        self.kbps
    }

    /// The sample period the application asks for \[µs\].
    pub fn period_us(&self) -> u64 {
        self.app.acquisition().period_us.max(1) as u64
    }

    /// The transmit queue (frames waiting for the controller).
    pub fn tx_queue(&self) -> &TxQueue<TX_QUEUE_LEN> {
        &self.txq
    }

    /// From now until `until_us` (board time) nothing the board sends is
    /// acknowledged (`None`: the bus works).
    pub fn set_bus_noack(&mut self, until_us: Option<u64>) {
        self.can.noack_until_us = until_us;
    }

    /// Whether a new image confirms itself after an update (`false`: it
    /// hangs at start and the bootloader rolls back).
    pub fn set_update_confirms(&mut self, confirms: bool) {
        self.confirms = confirms;
    }

    /// Handles a frame received from the bus at `now_us`; frames put on
    /// the bus go to `out`.
    pub fn handle(&mut self, f: &Frame, now_us: u64, out: &mut impl FnMut(Frame)) {
        if self.hung(now_us) {
            return;
        }
        let q = &mut self.txq;
        self.app.handle(f, now_us, &mut |o| {
            q.push(o);
        });
        self.transmit(now_us, out);
        self.after_update(now_us);
    }

    /// Runs the timers at `now_us`; frames put on the bus go to `out`.
    pub fn poll(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        if self.hung(now_us) {
            return;
        }
        let q = &mut self.txq;
        self.app.poll(now_us, &mut |o| {
            q.push(o);
        });
        self.transmit(now_us, out);
        self.after_update(now_us);
    }

    /// A hung new image: `true` until the watchdog resets the board.
    fn hung(&mut self, now_us: u64) -> bool {
        match self.hung_until {
            Some(t) if now_us < t => true,
            Some(_) => {
                self.hung_until = None;
                self.restart();
                false
            }
            None => false,
        }
    }

    /// After 0x1F51 "start": the restart into the new image; a new image
    /// that came up confirms itself (or hangs, see [`Self::set_update_confirms`]).
    fn after_update(&mut self, now_us: u64) {
        match self.app.program_mut().boot {
            BootState::SwapPending => {
                self.restart();
                if !self.confirms {
                    self.hung_until = Some(now_us + super::update::WATCHDOG_US);
                }
            }
            BootState::Trial if self.confirms => {
                // Nothing to report: RamProgram::mark_booted cannot fail.
                let _ = self.app.program_mut().mark_booted();
            }
            _ => {}
        }
    }

    /// A reset of the board (bootloader, then the application again).
    fn restart(&mut self) {
        super::update::reboot(&mut self.app, self.serial);
        self.txq = TxQueue::new();
    }

    /// Moves the queue through the controller onto the bus as far as the
    /// bus takes it; the counters go to the application.
    fn transmit(&mut self, now_us: u64, out: &mut impl FnMut(Frame)) {
        if let Some(c) = self.app.take_can_change() {
            self.kbps = (c.bitrate.bps() / 1000) as u16;
        }
        if let Some(k) = self.app.device_mut().take_bit_rate_switch() {
            self.kbps = k;
        }
        loop {
            self.txq.service(&mut self.can);
            if self.can.transmit(now_us, out) == 0 || self.txq.is_empty() {
                break;
            }
        }
        self.app.tx_stats(self.txq.stats(), now_us);
    }

    /// Takes and processes one ADC scan at `now_us`.
    pub fn sample(&mut self, now_us: u64) -> Output {
        let p = *self.app.pipeline().params();
        let counts = self.sim.sample(&p.transfer, &p.acq);
        self.app.on_sample(
            &Sample {
                counts,
                temp_c: self.sim.temp_c().map(|t| t as f32),
                t_s: None,
            },
            now_us,
        )
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::panic)]
mod tests {
    use super::*;
    use crate::board::sim::FaultKind;
    use perpend_can::status::{self, emcy};
    use perpend_core::geometry::Plane;

    const NODE: u8 = 0x11;

    struct Rig {
        b: VirtualBoard,
        t: u64,
        sent: Vec<Frame>,
    }

    impl Rig {
        fn new(plane: Plane<f64>, cfg: BoardConfig) -> Self {
            let sim = SimHead::new(Params::factory().head.cast(), plane, 0.002, 7).unwrap();
            let mut r = Rig {
                b: VirtualBoard::new(&cfg, sim).unwrap(),
                t: 0,
                sent: Vec::new(),
            };
            r.run(1);
            r
        }
        fn node(&self) -> u16 {
            self.b.app().device().node_id() as u16
        }
        /// Runs `n` sample periods (sample + poll each).
        fn run(&mut self, n: usize) {
            for _ in 0..n {
                self.t += self.b.period_us();
                self.b.sample(self.t);
                let s = &mut self.sent;
                self.b.poll(self.t, &mut |f| s.push(f));
            }
        }
        fn send(&mut self, f: Frame) -> Vec<Frame> {
            let mut v = Vec::new();
            self.b.handle(&f, self.t, &mut |f| v.push(f));
            self.sent.extend_from_slice(&v);
            v
        }
        fn sdo(&mut self, req: [u8; 8]) -> [u8; 8] {
            let id = 0x600 + self.node();
            let r = self.send(Frame::new(id, &req));
            r.iter().find(|f| f.id == 0x580 + self.node()).unwrap().data
        }
        fn write(&mut self, index: u16, sub: u8, v: &[u8]) -> u8 {
            let i = index.to_le_bytes();
            let mut req = [
                0x23 | (((4 - v.len()) as u8) << 2),
                i[0],
                i[1],
                sub,
                0,
                0,
                0,
                0,
            ];
            req[4..4 + v.len()].copy_from_slice(v);
            self.sdo(req)[0]
        }
    }

    fn plane() -> Plane<f64> {
        Plane::from_abcd(0.035, -0.052, 1.0, -40.0).unwrap()
    }

    fn cfg() -> BoardConfig {
        BoardConfig {
            node_id: NODE,
            head: None,
            calibration: None,
            thermal_tau_s: 0.0,
        }
    }

    #[test]
    fn tpdos_carry_the_plane_angles() {
        let mut r = Rig::new(plane(), cfg());
        assert_eq!(r.sent[0], Frame::new(0x700 + NODE as u16, &[0]));
        r.send(Frame::new(0, &[1, NODE]));
        r.run(20);
        let f = r.send(Frame::new(0x80, &[]));
        let t1 = f.iter().find(|f| f.id == 0x180 + NODE as u16).unwrap();
        let th1 = f32::from_le_bytes(t1.data[..4].try_into().unwrap()) as f64;
        let th2 = f32::from_le_bytes(t1.data[4..].try_into().unwrap()) as f64;
        // Tian eq. 1-3 through the TCS mapping: θ1 = atan2(n_y, −n_z),
        // θ2 = atan2(−n_x, −n_z) with n towards the head (−(a,b,c)).
        let n = -plane().n;
        assert!((th1 - n.y.atan2(-n.z).to_degrees()).abs() < 0.01, "{th1}");
        assert!(
            (th2 - (-n.x).atan2(-n.z).to_degrees()).abs() < 0.01,
            "{th2}"
        );
        let t2 = f.iter().find(|f| f.id == 0x280 + NODE as u16).unwrap();
        let st = u32::from_le_bytes(t2.data[..4].try_into().unwrap());
        assert_eq!(st & status::NO_PLANE, 0);
        assert_eq!(st & 0x1111, 0x1111);
    }

    #[test]
    fn a_faulted_sensor_raises_emcy_and_degrades() {
        let mut r = Rig::new(plane(), cfg());
        r.send(Frame::new(0, &[1, NODE]));
        r.run(5);
        r.b.sim_mut().set_fault(2, Some(FaultKind::Open));
        r.sent.clear();
        r.run(5);
        let e: Vec<_> = r
            .sent
            .iter()
            .filter(|f| f.id == 0x80 + NODE as u16)
            .collect();
        assert_eq!(e.len(), 1);
        assert_eq!(
            u16::from_le_bytes([e[0].data[0], e[0].data[1]]),
            emcy::sensor_current(2)
        );
        let st = r.b.app().device().status();
        assert_eq!(status::sensor_nibble(st, 2), status::SENSOR_OPEN_LOOP);
        assert_ne!(st & status::DEGRADED, 0);
        assert_eq!(st & status::NO_PLANE, 0);
    }

    #[test]
    fn a_bus_without_acknowledge_holds_nothing_up() {
        let mut r = Rig::new(plane(), cfg());
        r.send(Frame::new(0, &[1, NODE]));
        let n0 = r.b.app().device().sample_counter();
        r.b.set_bus_noack(Some(r.t + 2_000_500));
        r.sent.clear();
        for _ in 0..2000 {
            r.run(1);
            r.send(Frame::new(0x80, &[]));
        }
        assert!(r.sent.is_empty(), "{} frames acknowledged", r.sent.len());
        assert_eq!(r.b.app().device().sample_counter() - n0, 2000);
        let st = r.b.tx_queue().stats();
        assert_eq!(r.b.tx_queue().len(), TX_QUEUE_LEN);
        // 4 TPDOs per SYNC, 2 heartbeats, 2 EMCY (overflow, error reset)
        let produced = 2000 * 4 + 2 + 2;
        assert_eq!(
            st.dropped as usize,
            produced - VirtualCan::SLOTS - TX_QUEUE_LEN
        );
        // the fault is over: the queue drains, the next request is answered
        r.run(1);
        let got = r.sdo([0x40, 0x08, 0x20, 1, 0, 0, 0, 0]);
        assert_eq!(got[0], 0x43);
        assert_eq!(u32::from_le_bytes(got[4..].try_into().unwrap()), st.dropped);
        let emcy: Vec<_> = r
            .sent
            .iter()
            .filter(|f| f.id == 0x80 + NODE as u16)
            .collect();
        assert_eq!(emcy[0].data[..4], [0x10, 0x81, 0x11, 1]);
    }

    /// LSS requests to `app` at `t`; the LSS answers.
    fn lss(app: &mut HostApp, t: u64, reqs: &[[u8; 8]]) -> Vec<[u8; 8]> {
        let mut out = Vec::new();
        for r in reqs {
            app.handle(&Frame::new(0x7E5, r), t, &mut |f| {
                if f.id == 0x7E4 {
                    out.push(f.data)
                }
            });
        }
        out
    }

    /// `--params` with `thermal_tau_s`: stored in the record and 0x2105,
    /// applied by the booted board; out of range refused.
    #[test]
    fn seed_record_carries_the_thermal_time_constant() {
        let with_tau = BoardConfig {
            thermal_tau_s: 240.0,
            ..cfg()
        };
        let (p, img) = seed_record(&with_tau).unwrap().unwrap();
        assert_eq!(p.thermal_tau_s, 240.0);
        let mut store = host_store(HostFlash::new());
        save_with_tail(&mut store, &p, &img).unwrap();
        let app = App::with_serial(store, 9);
        assert_eq!(app.device().thermal_tau_s(), 240.0);
        assert_eq!(app.pipeline().params().thermal_tau_s, 240.0);
        let bad = BoardConfig {
            thermal_tau_s: -3.0,
            ..cfg()
        };
        let e = seed_record(&bad).unwrap_err().to_string();
        assert!(e.contains("thermal time constant"), "{e}");
    }

    #[test]
    fn lss_commissioning_of_a_non_configured_board_survives_a_power_cycle() {
        let cfg = BoardConfig {
            node_id: UNCONFIGURED,
            ..cfg()
        };
        let (p, img) = seed_record(&cfg).unwrap().unwrap();
        let mut store = host_store(HostFlash::new());
        save_with_tail(&mut store, &p, &img).unwrap();
        let mut app = App::with_serial(store, 9);
        let mut out = Vec::new();
        app.poll(0, &mut |f| out.push(f));
        app.poll(2_000_000, &mut |f| out.push(f));
        assert!(out.is_empty(), "non-configured: silent, {out:?}");
        assert!(app.device().lss_unconfigured());
        let got = lss(
            &mut app,
            2_000_100,
            &[
                [0x04, 1, 0, 0, 0, 0, 0, 0],
                [0x5E, 0, 0, 0, 0, 0, 0, 0],
                [0x11, 0x15, 0, 0, 0, 0, 0, 0],
                [0x13, 0, 3, 0, 0, 0, 0, 0],
                [0x17, 0, 0, 0, 0, 0, 0, 0],
                [0x04, 0, 0, 0, 0, 0, 0, 0],
            ],
        );
        let code = |c: u8, e: u8| [c, e, 0, 0, 0, 0, 0, 0];
        let want = [
            code(0x5E, 0xFF),
            code(0x11, 0),
            code(0x13, 0),
            code(0x17, 0),
        ];
        assert_eq!(got, want);
        assert_eq!(app.stores(), 1, "stored in the flash");
        app.poll(2_000_200, &mut |f| out.push(f));
        assert_eq!(out, vec![Frame::new(0x715, &[0])], "starts at once");
        // Power cycle: the stored node-id and bit rate.
        let mut app = App::with_serial(app.into_store(), 9);
        out.clear();
        app.poll(0, &mut |f| out.push(f));
        assert_eq!(out, vec![Frame::new(0x715, &[0])]);
        assert_eq!(
            app.can_config().bitrate,
            perpend_core::params::Bitrate::K250
        );
        assert_eq!(app.device().read_u32(0x1018, 4), Some(9));
    }

    #[test]
    fn stored_calibration_survives_reset_node() {
        let mut r = Rig::new(plane(), cfg());
        assert_eq!(r.write(0x2010, 0, &0x6C61_6375u32.to_le_bytes()), 0x60);
        assert_eq!(r.write(0x2101, 8, &0.001f32.to_le_bytes()), 0x60);
        assert_eq!(r.write(0x1010, 1, &0x6576_6173u32.to_le_bytes()), 0x60);
        assert_eq!(r.write(0x2101, 8, &0.002f32.to_le_bytes()), 0x60);
        r.send(Frame::new(0, &[0x81, NODE]));
        r.run(2);
        assert_eq!(r.node(), NODE as u16);
        assert_eq!(r.b.app().device().calibration(0).unwrap().gain, 0.001);
        assert_eq!(r.b.app().stores(), 1);
    }
}

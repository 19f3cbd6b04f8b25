//! `perpend cell`: the cell calibration script, end to end over the bus.
//!
//! ```text
//! perpend cell run --bus BUS --node-id N --sensors nominal.csv --plan plan.csv \
//!                  --robot sim:127.0.0.1:PORT|manual --out DIR [--truth truth.csv]
//! perpend cell sim-head --out DIR      nominal.csv + truth.csv of the paper's head
//! ```
//!
//! `run`, in this order, stopping at the first problem:
//! 1. **before**: at `--verify` fresh random poses inside the plan's reach
//!    (not the planned ones), the robot presents the datum plane, the
//!    tracker measures it, and the board's own normal, from θ1/θ2 of the
//!    TPDO that maps 0x2002 sub 1 and 2 (one frame: one sample), is compared
//!    with the tracker's plane over `--verify-samples` SYNCs (samples whose
//!    status says "no plane" are left out and counted). The uncalibrated
//!    head's spots miss the plane by more than the board's residual limit,
//!    so for this pass only the limit is raised (`--before-residual-mm`,
//!    0x2300 sub 4) and put back afterwards;
//! 2. **capture** every planned pose (`perpend node capture`, into
//!    `DIR/poses.csv`), **calibrate** (`perpend calibrate`, least squares,
//!    the paper's model, into `DIR/params.json`), **push** it (`perpend node
//!    push --preop`: write, verify, store, reset, verify, lock);
//! 3. **after**: the same fresh poses again, on the freshly reset board;
//! 4. the **floor**: what a perfectly calibrated board would show at those
//!    poses, computed host-side: the readings of the true head (`--truth`,
//!    for a simulation; without it the calibrated head stands in for it)
//!    with the reading noise the captures measured (pooled `s_mm`), fitted
//!    like the board fits them and compared with the same tracker planes.
//!
//! Figures (mean normal error over all verification samples, deg) are
//! printed and written to `DIR/cell.json`.
//!
//! Robots: `sim:HOST:PORT` moves the virtual board's plane through its
//! world channel (`perpend board --world`) and simulates the tracker
//! (Chen §5: 20 points, ξ = 0.02 mm); `manual` prints each pose and reads
//! the tracker's plane `A,B,C,D` from standard input after the operator
//! moved the robot. The bus part is the same for both, so the script runs
//! unchanged against a real board with `--bus socketcan:can0 --robot manual`.
//!
//! Limits: the board must be alone in running SYNC (the script sends it);
//! the board is left pre-operational with its new calibration.

use std::io::{BufRead, BufReader, Write as _};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_core::ext::Context;
use perpend_core::geometry::Plane;
use perpend_core::head::{Head4, Sensor};
use perpend_core::model::distance;
use perpend_core::normal::{plane as fit_plane, Method as FitMethod};
use perpend_lab::calibrate::angle_deg;
use perpend_lab::plan::PlannedPose;
use perpend_lab::sim::{gauss, Tracker};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::canopen::Nmt;
use crate::node::{capture, params, Node};

/// Arguments of `perpend cell`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// What to do.
    #[command(subcommand)]
    pub cmd: Cmd,
}

/// The subcommands.
#[derive(clap::Subcommand, Debug)]
pub enum Cmd {
    /// Before, capture, calibrate, push, after: the whole cell calibration.
    Run(RunArgs),
    /// Write the paper's simulated head: nominal.csv and truth.csv.
    SimHead(SimHeadArgs),
}

/// Options of `cell run`.
#[derive(clap::Args, Debug)]
pub struct RunArgs {
    /// The bus and the node.
    #[command(flatten)]
    pub link: crate::node::LinkArgs,
    /// The nominal head (sensors.csv) the calibration starts from.
    #[arg(long)]
    pub sensors: PathBuf,
    /// The poses to capture (`perpend plan --out`).
    #[arg(long)]
    pub plan: PathBuf,
    /// `sim:HOST:PORT` (the virtual board's world channel) or `manual`.
    #[arg(long)]
    pub robot: String,
    /// Directory for poses.csv, params.json and cell.json (must not hold a
    /// poses.csv yet).
    #[arg(long)]
    pub out: PathBuf,
    /// The true head (sensors.csv) for the floor; default: the calibrated one.
    #[arg(long)]
    pub truth: Option<PathBuf>,
    /// Samples averaged per captured pose.
    #[arg(long, default_value_t = 50)]
    pub samples: u32,
    /// Fresh verification poses.
    #[arg(long, default_value_t = 8)]
    pub verify: usize,
    /// SYNCs (board samples) per verification pose.
    #[arg(long, default_value_t = 20)]
    pub verify_samples: usize,
    /// How long the robot settles after a move before measuring [ms].
    #[arg(long, default_value_t = 300)]
    pub settle_ms: u64,
    /// Residual limit (0x2300 sub 4) during the before pass [mm]: the
    /// uncalibrated head's spots miss the plane by more than the board's
    /// default; put back afterwards.
    #[arg(long, default_value_t = 1.0)]
    pub before_residual_mm: f64,
    /// Seed of the verification poses and the simulated tracker.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
}

/// Options of `cell sim-head`.
#[derive(clap::Args, Debug)]
pub struct SimHeadArgs {
    /// Directory to write nominal.csv and truth.csv into.
    #[arg(long)]
    pub out: PathBuf,
}

/// What `cell run` measured (`cell.json`).
#[derive(Debug, Clone, PartialEq)]
pub struct Figures {
    /// Mean normal error before the calibration [deg].
    pub before_deg: f64,
    /// Mean normal error after it [deg].
    pub after_deg: f64,
    /// Mean normal error of the true head at the same poses [deg].
    pub floor_deg: f64,
    /// `after / floor`.
    pub ratio: f64,
    /// Where the floor's head came from (`truth` or `calibrated`).
    pub floor_head: String,
    /// Reading noise used for the floor [mm, 1σ].
    pub sigma_mm: f64,
    /// Poses captured and calibrated from.
    pub poses: usize,
    /// Verification poses.
    pub verify_poses: usize,
    /// Samples per verification pose.
    pub verify_samples: usize,
    /// Wall time of the run [s].
    pub seconds: f64,
}

/// One presented pose: the tracker's plane and, in a simulation, the
/// true one (else the tracker's again).
#[derive(Debug, Clone, Copy)]
struct Presented {
    tracker: Plane<f64>,
    truth: Plane<f64>,
}

/// The simulated robot and tracker.
struct SimRobot {
    stream: BufReader<TcpStream>,
    tracker: Tracker,
    rng: StdRng,
}

/// The robot (with its tracker) that presents the datum plane.
enum Robot {
    /// The virtual board's world channel and a simulated tracker.
    Sim(Box<SimRobot>),
    /// An operator moves the robot and types the tracker's plane.
    Manual,
}

impl Robot {
    fn open(spec: &str, seed: u64) -> Result<Self> {
        if spec == "manual" {
            return Ok(Robot::Manual);
        }
        let Some(addr) = spec.strip_prefix("sim:") else {
            bail!("--robot '{spec}': expected sim:HOST:PORT or manual");
        };
        let s = TcpStream::connect(addr)
            .with_context(|| format!("--robot {spec}: cannot reach the world channel"))?;
        s.set_read_timeout(Some(Duration::from_secs(5)))?;
        Ok(Robot::Sim(Box::new(SimRobot {
            stream: BufReader::new(s),
            tracker: Tracker::paper(),
            rng: StdRng::seed_from_u64(seed ^ 0x7472_6163),
        })))
    }

    /// Presents `pose` (called `label`) and measures it.
    fn present(&mut self, label: &str, pose: &PlannedPose) -> Result<Presented> {
        let truth = pose.plane();
        match self {
            Robot::Sim(sim) => {
                let SimRobot {
                    stream,
                    tracker,
                    rng,
                } = sim.as_mut();
                let line = format!("plane {}\n", abcd(&truth));
                stream.get_mut().write_all(line.as_bytes())?;
                let mut reply = String::new();
                stream
                    .read_line(&mut reply)
                    .context("the world channel did not answer")?;
                if reply.trim() != "ok" {
                    bail!("the world channel refused {label}: {}", reply.trim());
                }
                Ok(Presented {
                    tracker: tracker.measure(&truth, rng),
                    truth,
                })
            }
            Robot::Manual => {
                println!(
                    "{label}: move the datum plane to θ1 {:.3}°, θ2 {:.3}°, standoff {:.3} mm \
                     (plane {}), measure it with the tracker and type its A,B,C,D:",
                    pose.tilt_x_deg,
                    pose.tilt_y_deg,
                    pose.standoff_mm,
                    abcd(&truth)
                );
                let mut line = String::new();
                std::io::stdin().read_line(&mut line)?;
                let tracker = crate::demo::parse_plane(line.trim())?;
                Ok(Presented {
                    tracker,
                    truth: tracker,
                })
            }
        }
    }
}

/// `A,B,C,D` of a plane with enough digits.
fn abcd(p: &Plane<f64>) -> String {
    format!("{:.12},{:.12},{:.12},{:.9}", p.n.x, p.n.y, p.n.z, p.d)
}

/// Reads plan.csv (`pose, tilt_x_deg, tilt_y_deg, standoff_mm`, …).
fn read_plan(path: &Path) -> Result<Vec<(i64, PlannedPose)>> {
    let name = path.display().to_string();
    let mut rd = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .from_path(path)
        .with_context(|| format!("{name}: cannot read"))?;
    let header: Vec<String> = rd.headers()?.iter().map(|h| h.trim().into()).collect();
    let col = |c: &str| {
        header
            .iter()
            .position(|h| h == c)
            .ok_or_else(|| anyhow!("{name}: no column '{c}' (write it with `perpend plan`)"))
    };
    let cols = [
        col("pose")?,
        col("tilt_x_deg")?,
        col("tilt_y_deg")?,
        col("standoff_mm")?,
    ];
    let mut out = Vec::new();
    for rec in rd.records() {
        let rec = rec.with_context(|| format!("{name}: unreadable row"))?;
        let line = rec.position().map_or(0, |p| p.line());
        let v: Vec<f64> = cols
            .iter()
            .map(|&c| rec.get(c).and_then(|t| t.trim().parse::<f64>().ok()))
            .collect::<Option<_>>()
            .ok_or_else(|| anyhow!("{name}, line {line}: expected numbers"))?;
        let pose = PlannedPose {
            tilt_x_deg: v[1],
            tilt_y_deg: v[2],
            standoff_mm: v[3],
        };
        out.push((v[0] as i64, pose));
    }
    if out.len() < 6 {
        bail!(
            "{name}: {} poses; a calibration needs at least 6",
            out.len()
        );
    }
    Ok(out)
}

/// `count` random poses inside the bounding box of the plan.
fn fresh_poses(plan: &[(i64, PlannedPose)], count: usize, seed: u64) -> Vec<PlannedPose> {
    let range = |f: fn(&PlannedPose) -> f64| {
        plan.iter()
            .map(|(_, p)| f(p))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), x| {
                (lo.min(x), hi.max(x))
            })
    };
    let (tx, ty, s) = (
        range(|p| p.tilt_x_deg),
        range(|p| p.tilt_y_deg),
        range(|p| p.standoff_mm),
    );
    let mut rng = StdRng::seed_from_u64(seed);
    let mut draw = |(lo, hi): (f64, f64)| lo + (hi - lo) * rng.gen_range(0.0..=1.0);
    (0..count)
        .map(|_| PlannedPose {
            tilt_x_deg: draw(tx),
            tilt_y_deg: draw(ty),
            standoff_mm: draw(s),
        })
        .collect()
}

/// Angle [deg] between two normals, whatever their sign.
fn normal_error(a: &nalgebra::Vector3<f64>, b: &nalgebra::Vector3<f64>) -> f64 {
    let e = angle_deg(a, b);
    e.min(180.0 - e)
}

/// The board's normal from θ1/θ2 [deg] (Tian eq. 1-3 inverted).
fn normal_from_angles(th1: f64, th2: f64) -> nalgebra::Vector3<f64> {
    nalgebra::Vector3::new(-th2.to_radians().tan(), th1.to_radians().tan(), -1.0).normalize()
}

/// The synchronous TPDOs carrying θ1 and θ2 (0x2002 sub 1, 2, together)
/// and the status word (0x2005).
fn angle_pdos(node: &mut Node) -> Result<[crate::canopen::pdo::Tpdo; 2]> {
    let tpdos = node.client.read_tpdos(node.id, 4)?;
    let find = |subs: &[(u16, u8)]| {
        tpdos
            .iter()
            .find(|t| {
                let has = |i: u16, s: u8| t.mapped.iter().any(|m| m.index == i && m.sub == s);
                t.valid && t.synchronous() && subs.iter().all(|&(i, s)| has(i, s))
            })
            .cloned()
    };
    match (find(&[(0x2002, 1), (0x2002, 2)]), find(&[(0x2005, 0)])) {
        (Some(a), Some(s)) => Ok([a, s]),
        _ => bail!(
            "{}: no synchronous TPDOs with θ1 and θ2 (0x2002 sub 1, 2, in one) and the status \
             (0x2005); the default TPDOs 1 and 2 have them",
            node.name()
        ),
    }
}

/// The board's normal at one SYNC (θ1/θ2 from one frame); `None` when its
/// status says it has no plane.
fn board_normal(
    node: &mut Node,
    pdos: &[crate::canopen::pdo::Tpdo; 2],
) -> Result<Option<nalgebra::Vector3<f64>>> {
    node.client.sync()?;
    let mut values = std::collections::BTreeMap::new();
    for _ in 0..2 {
        let f = node
            .client
            .wait_for(Duration::from_secs(1), |f| {
                pdos.iter().any(|p| p.cob_id == f.id)
            })?
            .ok_or_else(|| anyhow!("{}: no TPDO after SYNC within 1 s", node.name()))?;
        for p in pdos.iter().filter(|p| p.cob_id == f.id) {
            for (m, v) in p.decode(f.payload()) {
                values.insert((m.index, m.sub), v.as_f64());
            }
        }
    }
    let get = |i, s| values.get(&(i, s)).copied();
    match (get(0x2002, 1), get(0x2002, 2), get(0x2005, 0)) {
        (Some(a), Some(b), Some(st)) if st as u32 & perpend_can::status::NO_PLANE == 0 => {
            Ok(Some(normal_from_angles(a, b)))
        }
        _ => Ok(None),
    }
}

/// The board's normals at one pose over `n` SYNCs, and how many SYNCs had
/// no plane.
fn board_normals(
    node: &mut Node,
    pdos: &[crate::canopen::pdo::Tpdo; 2],
    n: usize,
) -> Result<(Vec<nalgebra::Vector3<f64>>, usize)> {
    let mut out = Vec::with_capacity(n);
    while node.client.recv(Duration::ZERO)?.is_some() {}
    for _ in 0..n {
        if let Some(v) = board_normal(node, pdos)? {
            out.push(v);
        }
        // Spread the samples over the board's noise, not one sample twice.
        std::thread::sleep(Duration::from_millis(3));
    }
    let missing = n - out.len();
    Ok((out, missing))
}

/// One verification pass: the mean normal error [deg] and the presented
/// planes.
fn verify(
    node: &mut Node,
    robot: &mut Robot,
    poses: &[PlannedPose],
    a: &RunArgs,
    what: &str,
) -> Result<(f64, Vec<Presented>)> {
    let pdos = angle_pdos(node)?;
    node.client.nmt(node.id, Nmt::Start)?;
    let (mut sum, mut count, mut seen, mut missing) = (0.0, 0usize, Vec::new(), 0);
    for (k, pose) in poses.iter().enumerate() {
        let p = robot.present(&format!("{what}: verification pose {}", k + 1), pose)?;
        std::thread::sleep(Duration::from_millis(a.settle_ms));
        let (normals, miss) = board_normals(node, &pdos, a.verify_samples)?;
        for n in normals {
            sum += normal_error(&n, &p.tracker.n);
            count += 1;
        }
        missing += miss;
        seen.push(p);
    }
    node.client.nmt(node.id, Nmt::Preop)?;
    if count == 0 {
        bail!(
            "{what}: {} reported no plane at any verification pose",
            node.name()
        );
    }
    if missing > 0 {
        eprintln!(
            "warning: {what}: {missing} of {} samples without a plane, left out",
            count + missing
        );
    }
    Ok((sum / count as f64, seen))
}

/// The "before" pass. An uncalibrated head's spots are off the plane by
/// more than the board's residual limit (0x2300 sub 4) allows, so the board
/// would report no plane: the limit is raised to `--before-residual-mm`
/// for this pass and put back (and read back) afterwards, before anything
/// is stored.
fn verify_before(
    node: &mut Node,
    robot: &mut Robot,
    poses: &[PlannedPose],
    a: &RunArgs,
) -> Result<f64> {
    let id = node.id;
    let old = node.client.read_f32(id, 0x2300, 4)?;
    let raised = (a.before_residual_mm as f32).max(old);
    node.client
        .download(id, 0x2300, 4, &raised.to_le_bytes())
        .context("raising the residual limit (0x2300 sub 4) for the before pass")?;
    let res = verify(node, robot, poses, a, "before");
    let back = node
        .client
        .download(id, 0x2300, 4, &old.to_le_bytes())
        .map_err(anyhow::Error::from)
        .and_then(|()| Ok(node.client.read_f32(id, 0x2300, 4)?));
    match back {
        Ok(v) if v.to_bits() == old.to_bits() => res.map(|(e, _)| e),
        _ => bail!(
            "{}: the residual limit 0x2300 sub 4 could not be put back to {old} mm (it is not \
             stored: reset the node)",
            node.name()
        ),
    }
}

/// Captures every planned pose into `poses`.
fn capture_all(
    node: &mut Node,
    robot: &mut Robot,
    plan: &[(i64, PlannedPose)],
    a: &RunArgs,
    poses: &Path,
    cancel: &AtomicBool,
) -> Result<()> {
    for (k, pose) in plan {
        let p = robot.present(&format!("pose {k}"), pose)?;
        std::thread::sleep(Duration::from_millis(a.settle_ms));
        let c = capture::Args {
            plane: abcd(&p.tracker),
            pose: *k,
            out: poses.to_path_buf(),
            samples: a.samples,
        };
        capture::run(node, &c, cancel)?;
    }
    Ok(())
}

/// The pooled reading noise of the captures [mm, 1σ], 0 if none recorded.
fn pooled_sigma(poses: &Path) -> Result<f64> {
    let t = perpend_lab::exchange::read_poses(poses, None)?;
    let sd: Vec<f64> = t
        .rows
        .iter()
        .flat_map(|r| r.noise.sd_mm.iter().flatten().copied())
        .collect();
    if sd.is_empty() {
        return Ok(0.0);
    }
    Ok((sd.iter().map(|s| s * s).sum::<f64>() / sd.len() as f64).sqrt())
}

fn head4(v: Vec<Sensor<f64>>, what: &str) -> Result<Head4<f64>> {
    let n = v.len();
    let arr: [Sensor<f64>; 4] = v
        .try_into()
        .map_err(|_| anyhow!("{what}: 4 sensors expected, {n} found"))?;
    Ok(Head4::new(arr))
}

/// The floor: the mean normal error of `head` reading the true planes
/// with noise `sigma`, against the tracker's planes.
fn floor(head: &Head4<f64>, seen: &[Presented], sigma: f64, n: usize, seed: u64) -> Result<f64> {
    let mut rng = StdRng::seed_from_u64(seed ^ 0x666c_6f6f);
    let (mut sum, mut count) = (0.0, 0usize);
    for p in seen {
        for _ in 0..n {
            let mut r = [None; 4];
            for (i, x) in r.iter_mut().enumerate() {
                let d = distance(&head.sensors[i], &p.truth, i)
                    .map_err(|e| anyhow!("floor: sensor {} misses the plane: {e}", i + 1))?;
                *x = Some(d + sigma * gauss(&mut rng));
            }
            let fit = fit_plane(head, &r, &Context::default(), FitMethod::LeastSquares)
                .map_err(|e| anyhow!("floor: {e}"))?;
            sum += normal_error(&fit.normal, &p.tracker.n);
            count += 1;
        }
    }
    Ok(sum / count.max(1) as f64)
}

/// The head the floor is computed with, and where it came from.
fn floor_head(a: &RunArgs, params: &Path) -> Result<(Head4<f64>, String)> {
    match &a.truth {
        Some(p) => {
            let t = perpend_lab::exchange::read_sensors(p)?;
            Ok((
                head4(t.sensors()?, &p.display().to_string())?,
                "truth".into(),
            ))
        }
        None => {
            let f = perpend_lab::paramfile::ParamFile::read(params)?;
            let what = params.display().to_string();
            Ok((head4(f.sensors()?, &what)?, "calibrated".into()))
        }
    }
}

/// Calibrates `poses` from the nominal head into `params`.
fn calibrate(sensors: &Path, poses: &Path, params: &Path) -> Result<()> {
    use perpend_lab::calibrate as cal;
    cal::run(&cal::Args {
        sensors: sensors.to_path_buf(),
        poses: poses.to_path_buf(),
        method: cal::Method::Lsq,
        model: cal::Model::Base,
        out: Some(params.to_path_buf()),
        ekf_preset: cal::EkfPreset::Simulation,
        ekf_r: None,
        ekf_q: None,
        ekf_delta: None,
        ekf_nonlinear: false,
        ekf_joseph: false,
        keep_outliers: false,
    })
}

/// `perpend cell run`.
///
/// # Errors
/// Bad files or arguments, a board or robot that does not answer, a
/// calibration or push that fails; each in a sentence.
pub fn run_cell(a: &RunArgs, cancel: &AtomicBool) -> Result<Figures> {
    let started = Instant::now();
    if a.verify == 0 || a.verify_samples == 0 {
        bail!("--verify and --verify-samples must be at least 1");
    }
    let plan = read_plan(&a.plan)?;
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create", a.out.display()))?;
    let (poses, params) = (a.out.join("poses.csv"), a.out.join("params.json"));
    if poses.exists() {
        bail!(
            "{} exists: a cell run writes a fresh one (move it away or choose another --out)",
            poses.display()
        );
    }
    let mut robot = Robot::open(&a.robot, a.seed)?;
    let mut node = Node::connect(&a.link)?;
    node.hello()?;
    let fresh = fresh_poses(&plan, a.verify, a.seed);
    let before = verify_before(&mut node, &mut robot, &fresh, a)?;
    println!("cell: before calibration, normal error {before:.4}° (mean)");
    capture_all(&mut node, &mut robot, &plan, a, &poses, cancel)?;
    calibrate(&a.sensors, &poses, &params)?;
    let push = params::PushArgs {
        file: params.clone(),
        preop: true,
    };
    println!("{}", params::push(&mut node, &push, cancel)?);
    let (after, seen) = verify(&mut node, &mut robot, &fresh, a, "after")?;
    let sigma = pooled_sigma(&poses)?;
    let (head, from) = floor_head(a, &params)?;
    let floor = floor(&head, &seen, sigma, a.verify_samples, a.seed)?;
    Ok(Figures {
        before_deg: before,
        after_deg: after,
        floor_deg: floor,
        ratio: after / floor,
        floor_head: from,
        sigma_mm: sigma,
        poses: plan.len(),
        verify_poses: fresh.len(),
        verify_samples: a.verify_samples,
        seconds: started.elapsed().as_secs_f64(),
    })
}

impl Figures {
    /// The figures as the JSON object of `cell.json`.
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "before_deg": self.before_deg,
            "after_deg": self.after_deg,
            "floor_deg": self.floor_deg,
            "ratio": self.ratio,
            "floor_head": self.floor_head,
            "sigma_mm": self.sigma_mm,
            "poses": self.poses,
            "verify_poses": self.verify_poses,
            "verify_samples": self.verify_samples,
            "seconds": self.seconds,
        })
    }
}

/// Writes nominal.csv and truth.csv of the paper's head (Chen Table 2).
fn sim_head(a: &SimHeadArgs) -> Result<()> {
    let h = perpend_lab::sim::paper_head()?;
    std::fs::create_dir_all(&a.out)?;
    for (name, s) in [("nominal.csv", &h.nominal), ("truth.csv", &h.truth)] {
        let path = a.out.join(name);
        let table = perpend_lab::exchange::SensorTable::from_sensors(s, h.sigma_mm);
        let mut f = std::fs::File::create(&path)
            .with_context(|| format!("{}: cannot create", path.display()))?;
        perpend_lab::exchange::write_sensors(&mut f, &table, &[])?;
        println!("cell: wrote {}", path.display());
    }
    Ok(())
}

/// Runs `perpend cell`.
///
/// # Errors
/// As [`run_cell`] and [`sim_head`].
pub fn run(a: &Args) -> Result<()> {
    match &a.cmd {
        Cmd::SimHead(x) => sim_head(x),
        Cmd::Run(x) => {
            let cancel = AtomicBool::new(false);
            let f = run_cell(x, &cancel)?;
            let json = x.out.join("cell.json");
            std::fs::write(&json, serde_json::to_string_pretty(&f.json())?)
                .with_context(|| format!("{}: cannot write", json.display()))?;
            println!(
                "cell: normal error before {:.4}°, after {:.4}°, floor ({} head) {:.4}°: \
                 after/floor {:.2}× ({} poses captured, {} fresh poses × {} samples verified, \
                 {:.1} s); figures in {}",
                f.before_deg,
                f.after_deg,
                f.floor_head,
                f.floor_deg,
                f.ratio,
                f.poses,
                f.verify_poses,
                f.verify_samples,
                f.seconds,
                json.display()
            );
            Ok(())
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn angles_give_back_the_normal() {
        let pose = PlannedPose {
            tilt_x_deg: 3.0,
            tilt_y_deg: -2.0,
            standoff_mm: 28.0,
        };
        let n = normal_from_angles(3.0, -2.0);
        assert!(normal_error(&n, &pose.plane().n) < 1e-9);
        assert!(normal_error(&-n, &pose.plane().n) < 1e-9);
    }

    #[test]
    fn fresh_poses_stay_in_the_plan_box() {
        let p = |x, y, s| PlannedPose {
            tilt_x_deg: x,
            tilt_y_deg: y,
            standoff_mm: s,
        };
        let plan = vec![(1, p(-5.0, -4.0, 26.0)), (2, p(5.0, 4.0, 30.0))];
        for q in fresh_poses(&plan, 50, 3) {
            assert!((-5.0..=5.0).contains(&q.tilt_x_deg));
            assert!((-4.0..=4.0).contains(&q.tilt_y_deg));
            assert!((26.0..=30.0).contains(&q.standoff_mm));
        }
        assert!(Robot::open("robot", 1).is_err());
    }
}

//! The robot and tracker of a cell run or check: the virtual board's
//! world channel with a simulated tracker (Chen §5), or an operator who
//! moves the robot and types the tracker's plane.
//!
//! A typed plane goes through the checks `perpend node capture` makes
//! (issue 45): it must put every spot inside its sensor's measuring range
//! (the board's calibration and transfer functions,
//! [`crate::node::capture::plane_outside`], which also names a plane in
//! inches or micrometres) and lie near the planned pose (within
//! [`MANUAL_TILT_DEG`] of its tilt and [`MANUAL_STANDOFF_MM`] of its
//! standoff): else it is asked again, with why. A plane far from the plan
//! is a typo or a pose the robot did not reach; either would be taken
//! for a tracker blunder and left out, and the run's expected error
//! would no longer hold.

use std::io::{BufRead, BufReader, Write as _};
use std::net::TcpStream;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{anyhow, bail, Context as _, Result};
use perpend_calib::plan::PlannedPose;
use perpend_calib::sim::Tracker;
use perpend_core::geometry::Plane;
use perpend_core::head::Sensor;
use rand::rngs::StdRng;
use rand::SeedableRng;

/// Angle [deg] between two normals, whatever their sign.
pub fn normal_error(a: &nalgebra::Vector3<f64>, b: &nalgebra::Vector3<f64>) -> f64 {
    let e = perpend_calib::calibrate::angle_deg(a, b);
    e.min(180.0 - e)
}

/// Largest tilt between a typed plane and the planned pose [deg].
pub const MANUAL_TILT_DEG: f64 = 2.0;
/// Largest standoff difference between them [mm].
pub const MANUAL_STANDOFF_MM: f64 = 2.0;

/// What a typed plane is checked against besides the plan: the sensors
/// (the board's calibration) and their measuring ranges.
pub struct ManualCheck {
    /// The board's sensors.
    pub sensors: Vec<Sensor<f64>>,
    /// Their ranges [mm] (`None`: unknown, not judged).
    pub ranges: Vec<Option<(f64, f64)>>,
}

impl ManualCheck {
    /// From a parameter file with transfer functions (`node pull`).
    ///
    /// # Errors
    /// A file whose sensors do not read.
    pub fn from_params(f: &perpend_formats::paramfile::ParamFile) -> Result<Self> {
        Ok(Self {
            sensors: f.sensors()?,
            ranges: f
                .sensors
                .iter()
                .map(|s| {
                    let t = s.transfer.as_ref()?;
                    Some((t.mm_at_low.min(t.mm_at_high), t.mm_at_low.max(t.mm_at_high)))
                })
                .collect(),
        })
    }
}

/// Where the plane meets the spindle axis [mm] (`None`: parallel to it).
fn standoff(p: &Plane<f64>) -> Option<f64> {
    (p.n.z.abs() > 1e-9).then(|| -p.d / p.n.z)
}

/// The planned plane as the prompt prints it ([`rounded`]).
fn rounded(p: &Plane<f64>) -> String {
    format!("{:.4},{:.4},{:.4},{:.3}", p.n.x, p.n.y, p.n.z, p.d)
}

/// Whether `p` is the planned plane typed back (exactly, or as printed,
/// whose rounding moves it by under 0.006° and 3 µm): a tracker's
/// measurement is not within 0.01° and 5 µm of the plan (the robot alone
/// places the plane to about 0.1 mm; the tracker's own plane noise is
/// about 5 µm).
fn copied(p: &Plane<f64>, planned: &Plane<f64>) -> bool {
    let same_standoff = match (standoff(p), standoff(planned)) {
        (Some(a), Some(b)) => (a - b).abs() < 0.005,
        _ => false,
    };
    same_standoff && normal_error(&p.n, &planned.n) < 0.01
}

/// Why the typed plane `p` cannot be the tracker's plane of `pose`.
fn plausible(
    p: &Plane<f64>,
    pose: &PlannedPose,
    check: Option<&ManualCheck>,
) -> std::result::Result<(), String> {
    let planned = pose.plane();
    if copied(p, &planned) {
        return Err(
            "the planned plane as printed, not a measurement: measure the datum plane with the \
             tracker and type the plane it reports"
                .into(),
        );
    }
    if let (Some(s), Some(w)) = (standoff(p), standoff(&planned)) {
        for (k, unit) in [(25.4, "inches"), (0.001, "micrometres")] {
            // In other units when converted it lies near the plan (within
            // the standoff tolerance, or three times nearer than as typed,
            // for a pose off its plan): said before any range message.
            let (as_typed, converted) = ((s - w).abs(), (s * k - w).abs());
            let near = converted <= MANUAL_STANDOFF_MM || converted * 3.0 < as_typed;
            if near && as_typed > MANUAL_STANDOFF_MM {
                return Err(format!(
                    "a plane in {unit}: D = {} is {:.4} mm; type it in mm",
                    p.d,
                    p.d * k
                ));
            }
        }
    }
    if let Some(c) = check {
        let abcd = [p.n.x, p.n.y, p.n.z, p.d];
        if let Some(why) = crate::node::capture::plane_outside(&c.sensors, &c.ranges, abcd)
            .map_err(|e| format!("not a plane: {e}"))?
        {
            return Err(why);
        }
    }
    let tilt = normal_error(&p.n, &planned.n);
    if tilt > MANUAL_TILT_DEG {
        return Err(format!(
            "{tilt:.2}° from the planned pose's normal (at most {MANUAL_TILT_DEG}°): a typo, or the robot is not at this pose"
        ));
    }
    match (standoff(p), standoff(&planned)) {
        (Some(s), Some(w)) if (s - w).abs() > MANUAL_STANDOFF_MM => Err(format!(
            "at standoff {s:.2} mm, the plan's is {w:.2} mm (at most {MANUAL_STANDOFF_MM} mm apart): a typo, a plane in other units, or the robot is not at this pose"
        )),
        _ => Ok(()),
    }
}

impl Robot {
    /// Checks typed planes against the board's sensors and ranges too.
    pub fn check_manual(&mut self, c: ManualCheck) {
        if let Robot::Manual(_, check) = self {
            *check = Some(c);
        }
    }
}

/// One presented pose: the tracker's plane and, in a simulation, the
/// true one (else the tracker's again).
#[derive(Debug, Clone, Copy)]
pub struct Presented {
    /// The plane as the tracker measured it.
    pub tracker: Plane<f64>,
    /// The true plane (a simulation), else the tracker's again.
    pub truth: Plane<f64>,
}

/// The simulated robot and tracker.
pub struct SimRobot {
    stream: BufReader<TcpStream>,
    tracker: Tracker,
    rng: StdRng,
    /// The last joint of a `--reversal` run.
    pub turns: super::frames::Turns,
}

/// The robot (with its tracker) that presents the datum plane.
pub enum Robot {
    /// The virtual board's world channel and a simulated tracker.
    Sim(Box<SimRobot>),
    /// An operator moves the robot and types the tracker's plane.
    Manual(Lines, Option<ManualCheck>),
}

impl Robot {
    /// `sim:HOST:PORT` or `manual`; the simulated tracker is `tracker`.
    ///
    /// # Errors
    /// Another spec, a world channel that cannot be reached.
    pub fn open(spec: &str, seed: u64, tracker: Tracker) -> Result<Self> {
        if spec == "manual" {
            return Ok(Robot::Manual(Lines::stdin(), None));
        }
        let Some(addr) = spec.strip_prefix("sim:") else {
            bail!("--robot '{spec}': expected sim:HOST:PORT or manual");
        };
        let s = TcpStream::connect(addr)
            .with_context(|| format!("--robot {spec}: cannot reach the world channel"))?;
        s.set_read_timeout(Some(Duration::from_secs(5)))?;
        Ok(Robot::Sim(Box::new(SimRobot {
            stream: BufReader::new(s),
            tracker,
            rng: StdRng::seed_from_u64(seed ^ 0x7472_6163),
            turns: Default::default(),
        })))
    }

    /// The last joint of a `--reversal` run (`None` for a manual robot).
    pub fn turns(&mut self) -> Option<&mut super::frames::Turns> {
        match self {
            Robot::Sim(sim) => Some(&mut sim.turns).filter(|t| t.active()),
            Robot::Manual(..) => None,
        }
    }

    /// Presents `pose` (called `label`) and measures it.
    pub fn present(
        &mut self,
        label: &str,
        pose: &PlannedPose,
        cancel: &AtomicBool,
    ) -> Result<Presented> {
        let truth = pose.plane();
        match self {
            Robot::Sim(sim) => {
                let SimRobot {
                    stream,
                    tracker,
                    rng,
                    turns,
                } = sim.as_mut();
                world(stream, &turns.command(&truth), label)?;
                let seen = match turns.active() {
                    true => parse_tracker_plane(&world(stream, "seen\n", label)?)
                        .map_err(|e| anyhow!("the world's plane: {e}"))?,
                    false => truth,
                };
                Ok(Presented {
                    tracker: turns.correct(&tracker.measure(&truth, rng)),
                    truth: seen,
                })
            }
            Robot::Manual(lines, check) => {
                println!(
                    "{label}: move the datum plane to tilt x {:.3}°, tilt y {:.3}°, standoff \
                     {:.3} mm (planned plane {}), measure it with the tracker and type the \
                     plane it reports as A,B,C,D:",
                    pose.tilt_x_deg,
                    pose.tilt_y_deg,
                    pose.standoff_mm,
                    rounded(&truth)
                );
                let ok = |p: &Plane<f64>| plausible(p, pose, check.as_ref());
                let tracker = read_plane(label, &mut || lines.next(cancel, label), &ok)?;
                Ok(Presented {
                    tracker,
                    truth: tracker,
                })
            }
        }
    }
}

/// Sends `line` to the world channel; the reply after `ok`.
fn world(stream: &mut BufReader<TcpStream>, line: &str, label: &str) -> Result<String> {
    stream.get_mut().write_all(line.as_bytes())?;
    let mut reply = String::new();
    stream
        .read_line(&mut reply)
        .context("the world channel did not answer")?;
    match reply.trim().strip_prefix("ok") {
        Some(rest) => Ok(rest.trim().to_string()),
        None => bail!("the world channel refused {label}: {}", reply.trim()),
    }
}

/// The lines of standard input, read by a thread so that a Ctrl-C is
/// seen while the operator has not typed anything yet.
pub struct Lines(std::sync::mpsc::Receiver<std::io::Result<String>>);

impl Lines {
    /// Starts reading standard input.
    fn stdin() -> Self {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut input = std::io::stdin().lock();
            loop {
                let mut line = String::new();
                match input.read_line(&mut line) {
                    Ok(0) => break,
                    Ok(_) => {
                        if tx.send(Ok(line)).is_err() {
                            break;
                        }
                    }
                    Err(e) => {
                        let _ = tx.send(Err(e));
                        break;
                    }
                }
            }
        });
        Self(rx)
    }

    /// The next line; `None` at the end of input; an error on Ctrl-C.
    fn next(&self, cancel: &AtomicBool, label: &str) -> Result<Option<String>> {
        use std::sync::mpsc::RecvTimeoutError;
        loop {
            check_cancel(cancel, label)?;
            match self.0.recv_timeout(Duration::from_millis(100)) {
                Ok(line) => {
                    return Ok(Some(line.with_context(|| {
                        format!("reading the tracker's plane at {label}")
                    })?))
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => return Ok(None),
            }
        }
    }
}

/// Reads the tracker's plane for `label` from `next` (a line, `None` at
/// the end of input): a line it cannot read is asked again (saying why),
/// the end of input is an error.
fn read_plane(
    label: &str,
    next: &mut dyn FnMut() -> Result<Option<String>>,
    ok: &dyn Fn(&Plane<f64>) -> std::result::Result<(), String>,
) -> Result<Plane<f64>> {
    loop {
        let Some(line) = next()? else {
            bail!("reading the tracker's plane: end of input at {label}");
        };
        match parse_tracker_plane(line.trim()).and_then(|p| ok(&p).map(|()| p)) {
            Ok(p) => return Ok(p),
            Err(why) => println!(
                "{label}: '{}' refused: {why}; type the tracker's plane A,B,C,D again:",
                line.trim()
            ),
        }
    }
}

/// The tracker's plane from `A,B,C,D`, or why the line is not one.
pub fn parse_tracker_plane(t: &str) -> std::result::Result<Plane<f64>, String> {
    let v: Vec<f64> = t
        .split(',')
        .map(|x| x.trim().parse::<f64>().ok().filter(|x| x.is_finite()))
        .collect::<Option<_>>()
        .filter(|v: &Vec<f64>| v.len() == 4)
        .ok_or("not four numbers A,B,C,D")?;
    let norm = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    if norm == 0.0 {
        return Err("not a plane: |(A,B,C)| = 0".into());
    }
    Plane::from_abcd(v[0], v[1], v[2], v[3]).map_err(|e| format!("not a plane: {e}"))
}

/// `A,B,C,D` of a plane with enough digits.
pub fn abcd(p: &Plane<f64>) -> String {
    format!("{:.12},{:.12},{:.12},{:.9}", p.n.x, p.n.y, p.n.z, p.d)
}

/// Stops the run on Ctrl-C.
///
/// # Errors
/// Ctrl-C was pressed.
pub fn check_cancel(cancel: &AtomicBool, what: &str) -> Result<()> {
    if cancel.load(Ordering::SeqCst) {
        bail!("interrupted (Ctrl-C) during {what}");
    }
    Ok(())
}

/// Set by Ctrl-C during `cell run`: the run stops at its next step and
/// puts back what it changed.
pub static CANCEL: AtomicBool = AtomicBool::new(false);

/// The first Ctrl-C sets [`CANCEL`], the second quits at once.
pub fn install_ctrlc() {
    let _ = ctrlc::set_handler(|| {
        if CANCEL.swap(true, Ordering::SeqCst) {
            eprintln!("\nperpend cell: Ctrl-C, quitting now (nothing put back)");
            std::process::exit(130);
        }
        eprintln!(
            "\nperpend cell: Ctrl-C, stopping and putting back what the run changed (Ctrl-C \
             again quits at once)"
        );
    });
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn pose() -> PlannedPose {
        PlannedPose {
            tilt_x_deg: 0.0,
            tilt_y_deg: 0.0,
            standoff_mm: 28.0,
        }
    }

    #[test]
    fn manual_lines_are_asked_again_until_a_plane_or_the_end() {
        assert_eq!(
            parse_tracker_plane("hello").unwrap_err(),
            "not four numbers A,B,C,D"
        );
        assert_eq!(
            parse_tracker_plane("").unwrap_err(),
            "not four numbers A,B,C,D"
        );
        assert_eq!(
            parse_tracker_plane("1,2,3").unwrap_err(),
            "not four numbers A,B,C,D"
        );
        assert_eq!(
            parse_tracker_plane("0,0,0,5").unwrap_err(),
            "not a plane: |(A,B,C)| = 0"
        );
        let mut input = ["hello\n", "\n", "0,0,1,-28.02\n"].into_iter();
        let mut next = || Ok(input.next().map(String::from));
        let ok = |p: &Plane<f64>| plausible(p, &pose(), None);
        let p = read_plane("pose 1", &mut next, &ok).unwrap();
        assert!((p.d + 28.02).abs() < 1e-12);
        let e = read_plane("pose 2", &mut next, &ok)
            .unwrap_err()
            .to_string();
        assert_eq!(e, "reading the tracker's plane: end of input at pose 2");
    }

    /// The planes `node capture` refuses are refused here too: inches,
    /// `1,2,3,4`, a plane far from the planned pose.
    #[test]
    fn typed_planes_are_checked_like_captures_and_against_the_plan() {
        let head = perpend_calib::sim::paper_head().unwrap();
        let check = ManualCheck {
            sensors: head.nominal.clone(),
            ranges: vec![Some((20.0, 80.0)); 4],
        };
        let p = |s: &str| parse_tracker_plane(s).unwrap();
        let at = |s: &str| plausible(&p(s), &pose(), Some(&check));
        assert_eq!(at("0,0,1,-28.01"), Ok(()));
        // The plan typed back, exactly or as the prompt prints it, is no
        // measurement.
        let planned = pose().plane();
        for copy in [abcd(&planned), rounded(&planned)] {
            let e = at(&copy).unwrap_err();
            assert!(e.starts_with("the planned plane as printed"), "{copy}: {e}");
        }
        let inch = at("0,0,1,-1.1024").unwrap_err();
        assert!(
            inch.starts_with("a plane in inches: D = -1.1024 is -28.0010 mm"),
            "{inch}"
        );
        // A pose 5 mm off its plan, typed in inches: still said as inches
        // first, not as a plane outside the sensors' range.
        let off = at("0,0,1,-1.3000").unwrap_err();
        assert!(off.starts_with("a plane in inches"), "{off}");
        let e = at("1,2,3,4").unwrap_err();
        assert!(
            e.contains("measuring range") || e.contains("planned pose"),
            "{e}"
        );
        let tilted = at(&format!(
            "{},0,{},-28",
            3f64.to_radians().sin(),
            3f64.to_radians().cos()
        ))
        .unwrap_err();
        assert!(
            tilted.contains("from the planned pose's normal"),
            "{tilted}"
        );
        // Without ranges, the standoff still catches a far plane.
        let far = plausible(&p("0,0,1,-31"), &pose(), None).unwrap_err();
        assert!(far.contains("standoff 31.00 mm"), "{far}");
        // Asked again: the inch plane, then the right one.
        let mut input = ["0,0,1,-1.1024\n", "0,0,1,-28.1\n"].into_iter();
        let mut next = || Ok(input.next().map(String::from));
        let ok = |q: &Plane<f64>| plausible(q, &pose(), Some(&check));
        assert!((read_plane("pose 1", &mut next, &ok).unwrap().d + 28.1).abs() < 1e-9);
    }
}

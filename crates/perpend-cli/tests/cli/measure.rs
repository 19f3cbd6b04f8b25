//! `perpend measure` against the board's arithmetic (issue 14, item 4): for
//! the same readings of curved skins, the command's numbers equal those of
//! `perpend_core::surface::measure` in `f64` (the host's) and in `f32` (the
//! board's) within tolerance; rows that cannot be measured say why; errors
//! name the file and line, as JSON with `--json`.
#![allow(clippy::unwrap_used)]

use std::fmt::Write as _;
use std::path::Path;
use std::process::Command;

use nalgebra::Vector3;
use perpend_calib::sim::{curved_readings, simulate, tian_style_head, PoseSpread, SimConfig};
use perpend_core::calib::{fit_sensor_base, LsqConfig};
use perpend_core::ext::Context;
use perpend_core::head::Head4;
use perpend_core::normal::Method;
use perpend_core::surface::{measure, CurvedSurface, Shape};
use perpend_formats::exchange::{write_sensors, SensorTable};
use perpend_formats::paramfile::{ParamFile, SensorParams};
use rand::rngs::StdRng;
use rand::SeedableRng;

fn perpend(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_perpend"))
        .args(args)
        .output()
        .unwrap()
}

/// A calibrated Tian-style head (with a thermal extension on sensor 2, so
/// the row's temperature reaches the corrections) written as sensors.csv
/// and params.json.
fn write_head(dir: &Path, rng: &mut StdRng) -> (perpend_calib::sim::SimHead, Head4<f64>) {
    let head = tian_style_head(rng, 1.0, 0.02).unwrap();
    let cfg = SimConfig {
        spread: PoseSpread::cell(60.0),
        ..SimConfig::paper()
    };
    let data = simulate(&head, &cfg, &[], rng).unwrap();
    let mut pf = ParamFile::new("lsq", "base", data.poses.rows.len());
    for (i, s) in head.nominal.iter().enumerate() {
        let mut f = fit_sensor_base(s, i, &data.poses, &LsqConfig::default())
            .unwrap()
            .sensor;
        if i == 1 {
            f.ext.thermal = 0.004;
        }
        pf.sensors
            .push(SensorParams::from_sensor(i + 1, &f, Some(s)));
    }
    pf.write(&dir.join("params.json")).unwrap();
    let f = std::fs::File::create(dir.join("sensors.csv")).unwrap();
    write_sensors(f, &SensorTable::from_sensors(&head.nominal, None), &[]).unwrap();
    let calibrated = ParamFile::read(&dir.join("params.json"))
        .unwrap()
        .to_head::<4>()
        .unwrap();
    (head, calibrated)
}

/// Readings of `surfaces`, no plane columns, with a temperature; the last
/// row has two readings only.
fn write_readings(
    path: &Path,
    head: &perpend_calib::sim::SimHead,
    surfaces: &[CurvedSurface<f64>],
    rng: &mut StdRng,
) -> Vec<[Option<f64>; 4]> {
    let mut text = String::from("# curved skin\npose,d1_mm,d2_mm,d3_mm,d4_mm,temp_c\n");
    let mut rows = Vec::new();
    let cfg = SimConfig::paper();
    for (k, s) in surfaces.iter().enumerate() {
        let r = curved_readings(head, &cfg, s, rng);
        let mut r4 = [r[0], r[1], r[2], r[3]];
        if k == 3 {
            r4[0] = None;
        }
        if k + 1 == surfaces.len() {
            r4[1] = None;
            r4[3] = None;
        }
        let cell = |x: Option<f64>| x.map(|v| format!("{v}")).unwrap_or_default();
        let cells: Vec<String> = r4.iter().map(|x| cell(*x)).collect();
        writeln!(text, "{},{},{}", k + 1, cells.join(","), 20.0 + k as f64).unwrap();
        rows.push(r4);
    }
    std::fs::write(path, text).unwrap();
    rows
}

fn surfaces(shape: &Shape<f64>, rng: &mut StdRng) -> Vec<CurvedSurface<f64>> {
    use rand::Rng;
    (0..8)
        .map(|_| {
            let (t, a) = (
                rng.gen_range(0.0..10f64).to_radians(),
                rng.gen_range(0.0..std::f64::consts::TAU),
            );
            let n = Vector3::new(t.sin() * a.cos(), t.sin() * a.sin(), -t.cos());
            let p = Vector3::new(0.0, 0.0, rng.gen_range(57.0..63.0));
            CurvedSurface::through(p, n, shape).unwrap()
        })
        .collect()
}

/// `perpend measure --json` of `dir`'s sensors.csv, params.json and r.csv
/// on the surface `surface`.
fn measure_json(dir: &Path, surface: &str) -> serde_json::Value {
    let p = |name: &str| dir.join(name).to_str().unwrap().to_string();
    let out = perpend(&[
        "measure",
        "--sensors",
        &p("sensors.csv"),
        "--params",
        &p("params.json"),
        "--poses",
        &p("r.csv"),
        "--surface",
        surface,
        "--json",
    ]);
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap()
}

fn f(v: &serde_json::Value) -> f64 {
    v.as_f64().unwrap()
}

/// Checks one JSON row against the core in f64 (to rounding) and f32.
fn check_row(v: &serde_json::Value, head: &Head4<f64>, r: &[Option<f64>; 4], shape: &Shape<f64>) {
    let ctx = Context {
        temp_c: Some(19.0 + f(&v["pose"])),
        t_s: None,
    };
    let m64 = measure(head, r, &ctx, Method::LeastSquares, shape).unwrap();
    let n: Vec<f64> = v["normal"].as_array().unwrap().iter().map(f).collect();
    for (got, want) in n.iter().zip(m64.fit.normal.iter()) {
        assert!((got - want).abs() < 1e-12, "{v}");
    }
    let deg = |x: f64| x.to_degrees();
    for (key, want) in [
        ("theta1_deg", deg(m64.deviation.theta1)),
        ("theta2_deg", deg(m64.deviation.theta2)),
        ("theta_deg", deg(m64.deviation.theta)),
        ("pitch_deg", deg(m64.attitude.pitch)),
        ("yaw_deg", deg(m64.attitude.yaw)),
        ("rms_mm", m64.fit.rms),
    ] {
        assert!((f(&v[key]) - want).abs() < 1e-10, "{key}: {v}");
    }
    // The board's arithmetic: f32 head, readings and shape.
    let ctx32 = Context {
        temp_c: ctx.temp_c.map(|t| t as f32),
        t_s: None,
    };
    let r32 = r.map(|x| x.map(|d| d as f32));
    let m32 = measure(
        &head.cast::<f32>(),
        &r32,
        &ctx32,
        Method::LeastSquares,
        &shape.cast::<f32>(),
    )
    .unwrap();
    let n32: Vector3<f64> = m32.fit.normal.cast();
    let ang = Vector3::from_vec(n).angle(&n32).to_degrees();
    assert!(ang < 1e-3, "f32 normal {ang}° off: {v}");
    for (key, got) in [
        ("theta1_deg", m32.deviation.theta1.to_degrees()),
        ("theta2_deg", m32.deviation.theta2.to_degrees()),
        ("theta_deg", m32.deviation.theta.to_degrees()),
    ] {
        assert!((f(&v[key]) - got as f64).abs() < 1e-3, "f32 {key}: {v}");
    }
    assert!(
        (f(&v["rms_mm"]) - m32.fit.rms as f64).abs() < 1e-3,
        "f32 rms: {v}"
    );
    assert!(
        (f(&v["point_mm"][2]) - m32.fit.point.z as f64).abs() < 1e-2,
        "{v}"
    );
}

#[test]
fn measure_equals_the_core_in_f64_and_f32() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = StdRng::seed_from_u64(14);
    let (head, calibrated) = write_head(dir.path(), &mut rng);
    for (arg, shape) in [
        ("plane", Shape::Plane),
        ("sphere:600", Shape::Sphere { radius: 600.0 }),
        ("sphere:-450", Shape::Sphere { radius: -450.0 }),
        (
            "cylinder:350:0.6,0.8,0",
            Shape::Cylinder {
                radius: 350.0,
                axis: Vector3::new(0.6, 0.8, 0.0),
            },
        ),
    ] {
        let truth = match shape {
            Shape::Plane => Shape::Sphere { radius: 1e5 },
            s => s,
        };
        let surf = surfaces(&truth, &mut rng);
        let rows = write_readings(&dir.path().join("r.csv"), &head, &surf, &mut rng);
        let v = measure_json(dir.path(), arg);
        assert_eq!(v["measured"], 7, "{v}");
        assert_eq!(v["skipped"], 1);
        let json_rows = v["rows"].as_array().unwrap();
        for (k, (jr, r)) in json_rows.iter().zip(&rows).enumerate() {
            assert_eq!(jr["pose"], k as i64 + 1);
            assert_eq!(jr["line"], k as i64 + 3);
            if k + 1 == rows.len() {
                let e = jr["error"].as_str().unwrap();
                assert!(e.contains("2 valid readings"), "{e}");
                continue;
            }
            assert_eq!(jr["degraded"], k == 3);
            check_row(jr, &calibrated, r, &shape);
        }
        // The curved model measures the true normal at the axis point.
        if !matches!(shape, Shape::Plane) {
            let (_, n) = surf[0].axis_point().unwrap();
            let got: Vec<f64> = json_rows[0]["normal"]
                .as_array()
                .unwrap()
                .iter()
                .map(f)
                .collect();
            let ang = Vector3::from_vec(got).angle(&n).to_degrees();
            assert!(ang < 0.2, "{arg}: {ang}°");
        }
    }
}

#[test]
fn measure_text_and_errors() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = StdRng::seed_from_u64(15);
    let (head, _) = write_head(dir.path(), &mut rng);
    let p = |name: &str| dir.path().join(name).to_str().unwrap().to_string();
    let surf = surfaces(&Shape::Sphere { radius: 800.0 }, &mut rng);
    write_readings(&dir.path().join("r.csv"), &head, &surf, &mut rng);
    // Text: a table, and the skipped row on stderr with file and line.
    let out = perpend(&[
        "measure",
        "--sensors",
        &p("sensors.csv"),
        "--poses",
        &p("r.csv"),
        "--surface",
        "sphere:800",
    ]);
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    assert!(
        text.contains("θ1 [°]") && text.contains("uncalibrated"),
        "{text}"
    );
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(err.contains("r.csv, line 10: pose 8 skipped"), "{err}");
    // A malformed readings file: file and line, as JSON.
    std::fs::write(
        dir.path().join("bad.csv"),
        "pose,d1_mm,d2_mm,d3_mm,d4_mm\n1,40,41,x,40\n",
    )
    .unwrap();
    let out = perpend(&[
        "measure",
        "--sensors",
        &p("sensors.csv"),
        "--poses",
        &p("bad.csv"),
        "--json",
    ]);
    assert!(!out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(v["file"].as_str().unwrap().ends_with("bad.csv"), "{v}");
    assert_eq!(v["line"], 2);
    assert!(v["error"].as_str().unwrap().contains("column d3_mm"), "{v}");
    // No row measurable: an error naming the file.
    std::fs::write(
        dir.path().join("flat.csv"),
        "pose,d1_mm,d2_mm,d3_mm,d4_mm\n1,66,66,66,66\n",
    )
    .unwrap();
    let out = perpend(&[
        "measure",
        "--sensors",
        &p("sensors.csv"),
        "--poses",
        &p("flat.csv"),
        "--surface",
        "sphere:20",
        "--json",
    ]);
    assert!(!out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(
        v["error"]
            .as_str()
            .unwrap()
            .contains("no pose could be measured"),
        "{v}"
    );
    assert!(v["file"].as_str().unwrap().ends_with("flat.csv"), "{v}");
}

/// Issue 14's done-criterion: for the same readings, `perpend measure`
/// gives the numbers the board computes. The board here is
/// `perpend_board::app::App`, the logic the firmware and the virtual board
/// run: the sphere model set over CAN (0x2310), ADC counts of a 300 mm
/// sphere in, its outputs (readings, normal, θ1/θ2/θ, pitch/yaw, RMS) out;
/// the same readings and the board's head, written as files, go through
/// the command. The board computes in `f32`, the command in `f64`:
/// tolerances are those of `f32` rounding.
#[test]
fn measure_equals_the_board_for_the_same_readings() {
    use perpend_board::acq::{counts_for_signal, signal_for_mm};
    use perpend_board::app::App;
    use perpend_board::pipeline::Sample;
    use perpend_board::storage::{host_store, HostFlash};
    use perpend_can::Frame;

    let mut app = App::new(host_store(HostFlash::new()));
    let mut t = 100u64;
    app.poll(t, &mut |_| {}); // boot-up: pre-operational
                              // 0x2310 sub 2 = 300.0 mm, sub 1 = 1 (sphere), expedited SDO to node 0x20.
    for (sub, data) in [(2u8, 300f32.to_le_bytes()), (1, [1, 0, 0, 0])] {
        let len = if sub == 1 { 1 } else { 4 };
        let mut p = [0u8; 8];
        p[0] = 0x23 | ((4 - len as u8) << 2);
        p[1..3].copy_from_slice(&0x2310u16.to_le_bytes());
        p[3] = sub;
        p[4..4 + len].copy_from_slice(&data[..len]);
        let mut resp = Vec::new();
        t += 100;
        app.handle(&Frame::new(0x620, &p), t, &mut |f| resp.push(f));
        assert!(
            resp.iter().any(|f| f.id == 0x5A0 && f.data[0] == 0x60),
            "{resp:?}"
        );
    }
    let params = *app.pipeline().params();
    let head64 = params.head.cast::<f64>();

    let dir = tempfile::tempdir().unwrap();
    let mut pf = ParamFile::new("lsq", "base", 0);
    for (i, s) in head64.sensors.iter().enumerate() {
        pf.sensors
            .push(SensorParams::from_sensor(i + 1, s, Some(s)));
    }
    pf.write(&dir.path().join("params.json")).unwrap();
    let file = std::fs::File::create(dir.path().join("sensors.csv")).unwrap();
    write_sensors(file, &SensorTable::from_sensors(&head64.sensors, None), &[]).unwrap();

    let mut rng = StdRng::seed_from_u64(1414);
    let mut text = String::from("pose,d1_mm,d2_mm,d3_mm,d4_mm\n");
    let mut outs = Vec::new();
    for (k, s) in surfaces(&Shape::Sphere { radius: 300.0 }, &mut rng)
        .iter()
        .enumerate()
    {
        // the factory head's readings stay in range at 45 mm standoff
        let (p, n) = s.axis_point().unwrap();
        let s = CurvedSurface::through(p - Vector3::new(0.0, 0.0, 15.0), n, &s.shape()).unwrap();
        let mut counts = [0u16; 4];
        for (i, c) in counts.iter_mut().enumerate() {
            let d = s.distance(&head64.sensors[i], i).unwrap() as f32;
            let tr = &params.transfer[i];
            *c = counts_for_signal(signal_for_mm(d, tr), tr, &params.acq);
        }
        // The robot holds the pose: samples at 1 kHz, ±1 count of ADC
        // noise (identical counts would be a stuck sensor), until the jump
        // detector has accepted the new distances.
        let mut o = app.on_sample(&Sample::default(), t);
        for j in 0..8u16 {
            t += 1_000;
            let c = counts.map(|x| x + (j & 1));
            o = app.on_sample(
                &Sample {
                    counts: c,
                    ..Sample::default()
                },
                t,
            );
        }
        assert!(o.valid(), "{o:?}");
        let mm: Vec<String> = o
            .readings_mm
            .iter()
            .map(|x| format!("{}", *x as f64))
            .collect();
        writeln!(text, "{},{}", k + 1, mm.join(",")).unwrap();
        outs.push(o);
    }
    std::fs::write(dir.path().join("r.csv"), text).unwrap();
    let v = measure_json(dir.path(), "sphere:300");
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(rows.len(), outs.len(), "{v}");
    for (jr, o) in rows.iter().zip(&outs) {
        let n: Vec<f64> = jr["normal"].as_array().unwrap().iter().map(f).collect();
        let board = Vector3::new(o.normal[0] as f64, o.normal[1] as f64, o.normal[2] as f64);
        let ang = Vector3::from_vec(n).angle(&board).to_degrees();
        assert!(ang < 2e-4, "normal {ang}° apart: {jr}");
        for (key, got) in [
            ("theta1_deg", o.theta1_deg),
            ("theta2_deg", o.theta2_deg),
            ("theta_deg", o.theta_deg),
            ("pitch_deg", o.pitch_deg),
            ("yaw_deg", o.yaw_deg),
        ] {
            assert!(
                (f(&jr[key]) - got as f64).abs() < 2e-4,
                "{key}: board {got}, {jr}"
            );
        }
        assert!(
            (f(&jr["rms_mm"]) - o.rms_mm as f64).abs() < 1e-5,
            "rms: board {}, {jr}",
            o.rms_mm
        );
    }
}

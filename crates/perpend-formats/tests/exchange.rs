//! The exchange-format reader and writer on hand-written files.
#![allow(clippy::unwrap_used)]

use perpend_core::calib::Poses;
use perpend_formats::exchange::{parse_poses, parse_sensors, write_poses, write_sensors};

const SENSORS: &str = "\
# nominal head, written by hand
q,n,m,sensor,z_mm,y_mm,x_mm,comment
0.866,0,-0.5,1,0,0,50,first
# a comment between rows
0.866,-0.5,0,2,0,50,0,second
0.866,0,0.5,3,0,0,-50,
0.866,0.5,0,4,0,-50,0,
";

#[test]
fn sensors_in_any_column_order_with_comments() {
    let t = parse_sensors(SENSORS.as_bytes(), "sensors.csv").unwrap();
    assert_eq!(t.len(), 4);
    assert_eq!(t.rows[0].zero_mm, [50.0, 0.0, 0.0]);
    assert_eq!(t.rows[1].dir, [0.0, -0.5, 0.866]);
    assert_eq!(t.rows[3].sigma_mm, None);
    let s = t.sensors().unwrap();
    assert!((s[0].dir.norm() - 1.0).abs() < 1e-12);
}

#[test]
fn sensors_crlf_sigma_and_unsorted_rows() {
    let text = "sensor,x_mm,y_mm,z_mm,m,n,q,sigma_mm\r\n2,0,50,0,0,-0.5,0.866,0.002\r\n# c\r\n1,50,0,0,-0.5,0,0.866,\r\n3,-50,0,0,0.5,0,0.866,NaN\r\n";
    let t = parse_sensors(text.as_bytes(), "s.csv").unwrap();
    assert_eq!(t.rows[0].sensor, 1);
    assert_eq!(t.rows[0].sigma_mm, None);
    assert_eq!(t.rows[1].sigma_mm, Some(0.002));
    assert_eq!(t.rows[2].sigma_mm, None);
}

fn sensors_err(text: &str) -> String {
    parse_sensors(text.as_bytes(), "sensors.csv")
        .unwrap_err()
        .to_string()
}

#[test]
fn sensors_errors_name_file_line_and_problem() {
    assert_eq!(
        sensors_err("# head\nsensor,x_mm,y_mm,m,n,q\n1,0,0,0,0,1\n"),
        "sensors.csv, line 2: missing column z_mm"
    );
    assert_eq!(
        sensors_err("sensor,x_mm,y_mm,z_mm,m,n,q\n1,0,0,0,0,0,1\n# x\n2,abc,0,0,0,0,1\n"),
        "sensors.csv, line 4: column x_mm: 'abc' is not a valid number"
    );
    assert_eq!(
        sensors_err("sensor,x_mm,y_mm,z_mm,m,n,q\n1,0,0,0,0,0,0\n"),
        "sensors.csv, line 2: beam direction (m, n, q) has zero length"
    );
    assert_eq!(
        sensors_err("sensor,x_mm,y_mm,z_mm,m,n,q\n1,0,0,0,0,0,1\n1,1,0,0,0,0,1\n"),
        "sensors.csv, line 3: sensor 1 appears twice (also on line 2)"
    );
    assert_eq!(
        sensors_err("sensor,x_mm,y_mm,z_mm,m,n,q\n1,0,0,0,0,0,1\n3,1,0,0,0,0,1\n"),
        "sensors.csv, line 3: sensors must be numbered 1..2 without gaps: sensor 2 is missing"
    );
    assert_eq!(
        sensors_err("sensor,x_mm,y_mm,z_mm,m,n,q\n1,0,0,0,0,0\n"),
        "sensors.csv, line 2: 6 fields, but the header has 7"
    );
    assert_eq!(
        sensors_err("sensor,x_mm,y_mm,z_mm,m,n,q\n1,,0,0,0,0,1\n"),
        "sensors.csv, line 2: column x_mm: empty value"
    );
    assert_eq!(
        sensors_err("# only a comment\n"),
        "sensors.csv: empty file: no header row"
    );
}

const POSES: &str = "\
# calibration run
# columns in a free order, an unknown one, time and temperature
d3_mm,pose,extra,d1_mm,a,b,c,d_mm,d2_mm,t_s,d4_mm,temp_c
41.0,1,x,40.5,0,0,-1,30,41.2,0.0,40.9,21.5
,2,y,40.6,0,0.01,-1,30.1,41.0,1.5,41.0,
# between rows
41.3,5,z,40.7,0.01,0,-2,60,NaN,,41.2,22
";

#[test]
fn poses_free_order_missing_readings_and_context() {
    let t = parse_poses(POSES.as_bytes(), "poses.csv", Some(4)).unwrap();
    assert_eq!(t.n_sensors, 4);
    assert_eq!(t.rows.len(), 3);
    assert_eq!(
        t.rows[0].readings,
        vec![Some(40.5), Some(41.2), Some(41.0), Some(40.9)]
    );
    assert_eq!(
        t.rows[1].readings,
        vec![Some(40.6), Some(41.0), None, Some(41.0)]
    );
    assert_eq!(
        t.rows[2].readings,
        vec![Some(40.7), None, Some(41.3), Some(41.2)]
    );
    // missing readings are skipped, not zero
    assert_eq!(t.reading(1, 2), None);
    assert_eq!(t.rows[1].temp_c, None);
    assert_eq!(t.rows[1].t_s, Some(1.5));
    assert_eq!(t.context(2).temp_c, Some(22.0));
    assert_eq!(t.rows[2].pose, 5);
    assert_eq!(t.rows[2].line, 7);
    // (a, b, c) of any length: normalised together with d
    let p = t.plane(2);
    assert!((p.n.norm() - 1.0).abs() < 1e-12);
    assert!((p.d - 60.0 / (0.0001f64 + 4.0).sqrt()).abs() < 1e-12);
    // without the head's count, the columns decide
    assert_eq!(
        parse_poses(POSES.as_bytes(), "p", None).unwrap().n_sensors,
        4
    );
}

fn poses_err(text: &str, n: Option<usize>) -> String {
    parse_poses(text.as_bytes(), "poses.csv", n)
        .unwrap_err()
        .to_string()
}

#[test]
fn poses_errors_name_file_line_and_problem() {
    let h = "pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm\n";
    assert_eq!(
        poses_err(&format!("{h}1,0,0,1,-30,40,40,,\n"), Some(4)),
        "poses.csv: no pose has three valid readings: a normal needs three"
    );
    assert_eq!(
        poses_err(
            &format!("{h}1,0,0,1,-30,40,40,40,40\n# c\n2,0,0,0,-30,40,40,40,40\n"),
            Some(4)
        ),
        "poses.csv, line 4: degenerate plane normal: (a, b, c) has zero length"
    );
    assert_eq!(
        poses_err(&format!("{h}1,0,0,1,-30,40,4o,40,40\n"), Some(4)),
        "poses.csv, line 2: column d2_mm: '4o' is not a valid number"
    );
    assert_eq!(
        poses_err(&format!("{h}1,0,zero,1,-30,40,40,40,40\n"), Some(4)),
        "poses.csv, line 2: column b: 'zero' is not a valid number"
    );
    assert_eq!(
        poses_err(
            &format!(
                "{h}2,0,0,1,-30,40,40,40,40\n1,0,0,1,-30,40,40,40,40\n2,0,0,1,-31,40,40,40,40\n"
            ),
            Some(4)
        ),
        "poses.csv, line 4: pose 2 appears twice (also on line 2): pose numbers are unique"
    );
    assert_eq!(
        poses_err(&format!("{h}1,0,0,1,-30,40,-1,40,40\n"), Some(4)),
        "poses.csv, line 2: column d2_mm: negative distance -1 (readings are distances along the beam)"
    );
    assert_eq!(
        poses_err(
            "pose,a,b,c,d_mm,d1_mm,d2_mm,d4_mm\n1,0,0,1,-30,40,40,40\n",
            None
        ),
        "poses.csv, line 1: missing column d3_mm"
    );
    assert_eq!(
        poses_err(&format!("{h}1,0,0,1,-30,40,40,40,40\n"), Some(3)),
        "poses.csv, line 1: column d4_mm: the head has only 3 sensors"
    );
    assert_eq!(
        poses_err("# c\npose,a,b,d_mm,d1_mm\n", None),
        "poses.csv, line 2: missing column c"
    );
    assert_eq!(poses_err(h, Some(4)), "poses.csv: no pose rows");
    assert_eq!(
        poses_err(&format!("{h}1,0,0,1,-30,40,40,inf,40\n"), Some(4)),
        "poses.csv, line 2: column d3_mm: reading must be finite or empty, got 'inf'"
    );
}

#[test]
fn write_then_read_round_trips() {
    let s = parse_sensors(SENSORS.as_bytes(), "s").unwrap();
    let p = parse_poses(POSES.as_bytes(), "p", Some(4)).unwrap();
    let mut sb = Vec::new();
    write_sensors(&mut sb, &s, &["a comment".into()]).unwrap();
    let mut pb = Vec::new();
    write_poses(&mut pb, &p, &[]).unwrap();
    let s2 = parse_sensors(sb.as_slice(), "s").unwrap();
    let p2 = parse_poses(pb.as_slice(), "p", Some(4)).unwrap();
    assert_eq!(s2, s);
    assert_eq!(p2.rows.len(), p.rows.len());
    for (a, b) in p.rows.iter().zip(p2.rows.iter()) {
        assert_eq!(a.readings, b.readings);
        assert_eq!(a.abcd, b.abcd);
        assert_eq!(a.t_s, b.t_s);
        assert_eq!(a.temp_c, b.temp_c);
    }
    assert!(String::from_utf8(sb)
        .unwrap()
        .starts_with("# a comment\nsensor,"));
}

/// `../shared/data-format.md`: rows in any order (sorted by pose), a pose
/// with fewer than three valid readings kept, the optional noise columns
/// read and written back.
#[test]
fn unsorted_rows_short_poses_and_noise_columns() {
    let text = "\
pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm,s1_mm,s2_mm,s3_mm,s4_mm,n_samples,plane_rms_mm,plane_points
3,0,0,1,-30,40,40,40,40,0.01,0.02,0.01,0.01,16,0.012,20
1,0,0,1,-31,41,41,,,0.01,0.02,,,16,0.011,20
2,0,0,1,-32,42,42,42,42,0.01,0.02,0.01,0.01,16,0.013,20
";
    let t = parse_poses(text.as_bytes(), "p", Some(4)).unwrap();
    let order: Vec<i64> = t.rows.iter().map(|r| r.pose).collect();
    assert_eq!(order, vec![1, 2, 3]);
    assert_eq!(t.rows[0].readings, vec![Some(41.0), Some(41.0), None, None]);
    assert_eq!(t.rows[0].line, 3);
    assert_eq!(
        t.rows[2].noise.sd_mm,
        vec![Some(0.01), Some(0.02), Some(0.01), Some(0.01)]
    );
    assert_eq!(t.rows[0].noise.sd_mm[2], None);
    assert_eq!(t.rows[1].noise.n_samples, Some(16));
    assert_eq!(t.rows[1].noise.plane_rms_mm, Some(0.013));
    assert_eq!(t.rows[1].noise.plane_points, Some(20));
    let mut out = Vec::new();
    write_poses(&mut out, &t, &[]).unwrap();
    let back = parse_poses(out.as_slice(), "back", Some(4)).unwrap();
    assert_eq!(back.rows.len(), 3);
    for (a, b) in t.rows.iter().zip(&back.rows) {
        assert_eq!(
            (a.pose, &a.readings, &a.noise),
            (b.pose, &b.readings, &b.noise)
        );
    }
    // s columns come all or none
    let partial = "pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,s1_mm\n1,0,0,1,-30,40,40,40,0.01\n";
    let e = parse_poses(partial.as_bytes(), "p", Some(3))
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing column s2_mm"), "{e}");
}

#[test]
fn readings_without_a_plane_and_with_an_ignored_one() {
    use perpend_formats::exchange::parse_readings;
    // No plane columns, context columns, rows out of order.
    let text = "# readings of a curved skin\nd2_mm,pose,d1_mm,d3_mm,temp_c,t_s\n40.5,2,41,42,21.5,0.1\n# c\n40,1,,41.5,,\n";
    let t = parse_readings(text.as_bytes(), "r.csv", Some(3)).unwrap();
    assert_eq!(t.n_sensors, 3);
    assert_eq!(t.rows[0].pose, 1);
    assert_eq!(t.rows[0].line, 5);
    assert_eq!(t.rows[0].readings, vec![None, Some(40.0), Some(41.5)]);
    assert_eq!(t.rows[1].context().temp_c, Some(21.5));
    assert_eq!(t.rows[1].context().t_s, Some(0.1));
    // A calibration file: its plane columns are not even parsed.
    let text = "pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm\n1,junk,0,1,-40,40,41,42\n";
    let t = parse_readings(text.as_bytes(), "p.csv", None).unwrap();
    assert_eq!(t.rows[0].readings, vec![Some(40.0), Some(41.0), Some(42.0)]);
}

#[test]
fn readings_errors_name_file_line_and_problem() {
    use perpend_formats::exchange::parse_readings;
    let e = |text: &str| {
        parse_readings(text.as_bytes(), "r.csv", Some(3))
            .unwrap_err()
            .to_string()
    };
    assert_eq!(
        e("d1_mm,d2_mm,d3_mm\n1,2,3\n"),
        "r.csv, line 1: missing column pose"
    );
    assert_eq!(
        e("pose,d1_mm,d2_mm\n1,2,3\n"),
        "r.csv, line 1: missing column d3_mm"
    );
    assert_eq!(
        e("pose,d1_mm,d2_mm,d3_mm\n1,40,41,42\n# c\n1,40,41,42\n"),
        "r.csv, line 4: pose 1 appears twice (also on line 2): pose numbers are unique"
    );
    assert_eq!(
        e("pose,d1_mm,d2_mm,d3_mm\n1,40,-1,42\n"),
        "r.csv, line 2: column d2_mm: negative distance -1 (readings are distances along the beam)"
    );
    assert_eq!(
        e("pose,d1_mm,d2_mm,d3_mm\n1,40,,42\n"),
        "r.csv: no pose has three valid readings: a normal needs three"
    );
    assert_eq!(e("pose,d1_mm,d2_mm,d3_mm\n"), "r.csv: no pose rows");
}

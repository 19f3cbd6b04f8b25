//! Line numbers in the readers' messages count physical lines whatever the
//! line ending: LF, CRLF, a bare CR (old Mac), a last line without a
//! newline, a UTF-8 byte-order mark. Each case writes the same file with
//! every ending and expects the message of the LF file, word for word.
#![allow(clippy::unwrap_used)]

use perpend_formats::exchange::{parse_poses, parse_readings, parse_sensors};

/// A transform of an LF text into the bytes of another ending.
type Ending = Box<dyn Fn(&str) -> Vec<u8>>;

/// The ways a file's lines may end, as (name, transform of an LF text).
fn endings() -> Vec<(&'static str, Ending)> {
    vec![
        ("LF", Box::new(|t: &str| t.as_bytes().to_vec())),
        (
            "CRLF",
            Box::new(|t: &str| t.replace('\n', "\r\n").into_bytes()),
        ),
        ("CR", Box::new(|t: &str| t.replace('\n', "\r").into_bytes())),
        (
            "no final newline",
            Box::new(|t: &str| t.trim_end_matches('\n').as_bytes().to_vec()),
        ),
        (
            "BOM + CRLF",
            Box::new(|t: &str| {
                let mut b = vec![0xEF, 0xBB, 0xBF];
                b.extend(t.replace('\n', "\r\n").into_bytes());
                b
            }),
        ),
        (
            "CRLF, no final newline",
            Box::new(|t: &str| t.trim_end_matches('\n').replace('\n', "\r\n").into_bytes()),
        ),
    ]
}

/// Checks that `parse` gives `expected` for `lf` written with every ending.
fn same_message(lf: &str, expected: &str, parse: impl Fn(&[u8]) -> String) {
    for (name, f) in endings() {
        assert_eq!(parse(&f(lf)), expected, "line ending {name}");
    }
}

fn poses(b: &[u8]) -> String {
    parse_poses(b, "poses.csv", Some(4))
        .unwrap_err()
        .to_string()
}

fn sensors(b: &[u8]) -> String {
    parse_sensors(b, "sensors.csv").unwrap_err().to_string()
}

fn readings(b: &[u8]) -> String {
    parse_readings(b, "readings.csv", Some(4))
        .unwrap_err()
        .to_string()
}

const PH: &str = "pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm\n";

#[test]
fn a_bad_number_on_line_4_is_on_line_4() {
    let lf = format!(
        "# run 7\n{PH}1,0,0,1,-30,40,40,40,40\n2,0,0,1,-30,12.3.4,40,40,40\n3,0,0,1,-30,40,40,40,40\n"
    );
    same_message(
        &lf,
        "poses.csv, line 4: column d1_mm: '12.3.4' is not a valid number",
        poses,
    );
}

#[test]
fn a_bad_number_on_the_last_line_is_on_that_line() {
    let lf = format!("{PH}1,0,0,1,-30,40,40,40,40\n2,0,0,1,-30,40,40,40,x\n");
    same_message(
        &lf,
        "poses.csv, line 3: column d4_mm: 'x' is not a valid number",
        poses,
    );
}

#[test]
fn duplicate_poses_name_both_physical_lines() {
    let lf = format!("{PH}1,0,0,1,-30,40,40,40,40\n\n# gap\n1,0,0,1,-31,40,40,40,40\n");
    same_message(
        &lf,
        "poses.csv, line 5: pose 1 appears twice (also on line 2): pose numbers are unique",
        poses,
    );
}

#[test]
fn a_short_row_is_on_its_line() {
    let lf = format!("{PH}1,0,0,1,-30,40,40,40,40\n2,0,0,1,-30,40,40,40\n");
    same_message(
        &lf,
        "poses.csv, line 3: 8 fields, but the header has 9",
        poses,
    );
}

#[test]
fn sensors_errors_count_physical_lines() {
    let h = "# head\nsensor,x_mm,y_mm,z_mm,m,n,q\n";
    same_message(
        &format!("{h}1,50,0,0,0,0,1\n2,0,50,0,0,0,1\n2,0,-50,0,0,0,1\n"),
        "sensors.csv, line 5: sensor 2 appears twice (also on line 4)",
        sensors,
    );
    same_message(
        &format!("{h}1,50,0,0,0,0,1\n\n2,0,5o,0,0,0,1\n"),
        "sensors.csv, line 5: column y_mm: '5o' is not a valid number",
        sensors,
    );
    same_message(
        &format!("{h}1,50,0,0,0,0,1\n2,0,50,0,0,0\n"),
        "sensors.csv, line 4: 6 fields, but the header has 7",
        sensors,
    );
}

#[test]
fn readings_errors_count_physical_lines() {
    let h = "# measured\npose,d1_mm,d2_mm,d3_mm,d4_mm\n";
    same_message(
        &format!("{h}1,40,40,40,40\n# c\n2,40,40,4..0,40\n"),
        "readings.csv, line 5: column d3_mm: '4..0' is not a valid number",
        readings,
    );
    same_message(
        &format!("{h}1,40,40,40,40\n1,40,40,40,41\n"),
        "readings.csv, line 4: pose 1 appears twice (also on line 3): pose numbers are unique",
        readings,
    );
}

#[test]
fn a_missing_column_is_on_the_header_line() {
    same_message(
        "# c\n# d\npose,a,b,d_mm,d1_mm,d2_mm,d3_mm,d4_mm\n1,0,0,-30,40,40,40,40\n",
        "poses.csv, line 3: missing column c",
        poses,
    );
}

#[test]
fn every_ending_reads_the_same_table() {
    let lf = format!("# c\n{PH}2,0,0,1,-30,40,41,42,43\n1,0,0,1,-29,,41,42,43\n");
    let want = parse_poses(lf.as_bytes(), "p", Some(4)).unwrap();
    for (name, f) in endings() {
        let got = parse_poses(f(&lf).as_slice(), "p", Some(4)).unwrap();
        assert_eq!(got.rows.len(), want.rows.len(), "{name}");
        for (g, w) in got.rows.iter().zip(&want.rows) {
            assert_eq!((g.pose, &g.readings), (w.pose, &w.readings), "{name}");
        }
    }
}

/// `params.json`: a syntax error on line 3 is reported on line 3 with every
/// ending, and a valid file with a byte-order mark or bare CRs reads.
#[test]
fn params_json_errors_count_physical_lines() {
    use perpend_formats::paramfile::ParamFile;
    let head = perpend_core::head::Head4::cone(50.0, 0.5, 0.0, 0.0).unwrap();
    let good =
        serde_json::to_string_pretty(&ParamFile::truth(&head.sensors, &head.sensors)).unwrap();
    let want = ParamFile::parse(&good, "p.json").unwrap();
    // Line 3 of the pretty file gets a stray character.
    let mut lines: Vec<String> = good.lines().map(str::to_string).collect();
    lines[2].push('x');
    let bad = lines.join("\n") + "\n";
    for (name, f) in endings() {
        let text = String::from_utf8(f(&good)).unwrap();
        assert_eq!(ParamFile::parse(&text, "p.json").unwrap(), want, "{name}");
        let text = String::from_utf8(f(&bad)).unwrap();
        let e = format!("{:#}", ParamFile::parse(&text, "p.json").unwrap_err());
        assert!(e.contains("p.json") && e.contains("line 3"), "{name}: {e}");
    }
}

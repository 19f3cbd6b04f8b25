#!/usr/bin/env python3
"""Writes the corpus of bad input files and its manifest (standard library
only): each case is a file the readers must refuse (or, for `run-left` and
`readings-left`, accept with a reading left out), with the message it must
produce (file, line, cause). `cases.tsv` columns: file, reader, the texts
the message must contain (several joined by `&&`). Readers (crates/perpend-formats/tests/corpus_readers.rs):
sensors, poses, readings (4 sensors), params, run (poses.csv checked against
head.csv: plausibility), run-left (a reading left out: first warning lines),
readings-left (a readings file against head.csv).
Run `python3 make.py` after changing a case; the files are committed."""
import math
import os

HERE = os.path.dirname(os.path.abspath(__file__))
CASES = []


def case(name, reader, expect, text, raw=None):
    data = raw if raw is not None else text.encode()
    with open(os.path.join(HERE, name), "wb") as f:
        f.write(data)
    CASES.append((name, reader, expect))


def crlf(t):
    return t.replace("\n", "\r\n")


# The paper's nominal head in the TCS (sensors.csv of `perpend simulate`).
HEAD = [((50, 0, 0), (-0.5, 0, 0.866)), ((0, -50, 0), (0, 0.5, 0.866)),
        ((-50, 0, 0), (0.5, 0, 0.866)), ((0, 50, 0), (0, -0.5, 0.866))]
head_csv = "sensor,x_mm,y_mm,z_mm,m,n,q,sigma_mm\n" + "".join(
    f"{i + 1},{e[0]},{e[1]},{e[2]},{u[0]},{u[1]},{u[2]},0.01\n" for i, (e, u) in enumerate(HEAD))
with open(os.path.join(HERE, "head.csv"), "w") as f:
    f.write(head_csv)


def poses(reading_k=1.0, plane_k=1.0, wild=None):
    """Eight poses of planes tilted up to 5 deg at a 36 mm standoff, the
    readings the nominal head gives, readings x reading_k, offsets x plane_k;
    wild = (pose, sensor, factor) multiplies one reading."""
    rows = ["pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm"]
    for k in range(8):
        tx, ty = math.radians(5 * math.cos(k)), math.radians(5 * math.sin(k))
        n = (-math.sin(ty), math.sin(tx), -math.cos(tx) * math.cos(ty))
        s = 36 + (k % 3) - 1
        d = -n[2] * s
        rd = []
        for i, (e, u) in enumerate(HEAD):
            nu = sum(a * b for a, b in zip(n, u)) / math.sqrt(sum(x * x for x in u))
            r = -(sum(a * b for a, b in zip(n, e)) + d) / nu * reading_k
            if wild and wild[0] == k + 1 and wild[1] == i + 1:
                r *= wild[2]
            rd.append(f"{r:.4f}")
        rows.append(f"{k + 1},{n[0]:.6f},{n[1]:.6f},{n[2]:.6f},{d * plane_k:.4f}," + ",".join(rd))
    return "\n".join(rows) + "\n"


P = "pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm\n"
R1 = "1,0,0,1,-30,40,40,40,40\n"
S = "sensor,x_mm,y_mm,z_mm,m,n,q\n"

# Line endings (issue 31: CRLF reported every error one line early).
case("poses_crlf_bad_number.csv", "poses",
     "poses_crlf_bad_number.csv, line 4: column d1_mm: '12.3.4' is not a valid number",
     crlf("# run 7\n" + P + R1 + "2,0,0,1,-30,12.3.4,40,40,40\n"))
case("poses_crlf_duplicate.csv", "poses",
     "poses_crlf_duplicate.csv, line 5: pose 1 appears twice (also on line 2)",
     crlf(P + R1 + "\n# gap\n" + "1,0,0,1,-31,40,40,40,40\n"))
case("poses_crlf_short_row.csv", "poses",
     "poses_crlf_short_row.csv, line 3: 8 fields, but the header has 9",
     crlf(P + R1 + "2,0,0,1,-30,40,40,40\n"))
case("sensors_crlf_duplicate.csv", "sensors",
     "sensors_crlf_duplicate.csv, line 5: sensor 2 appears twice (also on line 4)",
     crlf("# head\n" + S + "1,50,0,0,0,0,1\n2,0,50,0,0,0,1\n2,0,-50,0,0,0,1\n"))
case("poses_bom_comment.csv", "poses",
     "poses_bom_comment.csv, line 3: missing column c",
     None, b"\xef\xbb\xbf" + crlf("# c\n# d\npose,a,b,d_mm,d1_mm,d2_mm,d3_mm,d4_mm\n").encode())
case("poses_cr_only.csv", "poses",
     "poses_cr_only.csv, line 4: column d3_mm: '4o' is not a valid number",
     ("# old Mac\n" + P + R1 + "2,0,0,1,-30,40,40,4o,40\n").replace("\n", "\r"))
case("poses_no_final_newline.csv", "poses",
     "poses_no_final_newline.csv, line 3: column d4_mm: 'x' is not a valid number",
     P + R1 + "2,0,0,1,-30,40,40,40,x")
case("readings_crlf_bad.csv", "readings",
     "readings_crlf_bad.csv, line 5: column d3_mm: '4..0' is not a valid number",
     crlf("# measured\npose,d1_mm,d2_mm,d3_mm,d4_mm\n1,40,40,40,40\n# c\n2,40,40,4..0,40\n"))
case("readings_duplicate.csv", "readings",
     "readings_duplicate.csv, line 3: pose 1 appears twice (also on line 2)",
     "pose,d1_mm,d2_mm,d3_mm,d4_mm\n1,40,40,40,40\n1,40,40,40,41\n")
case("params_crlf_syntax.json", "params",
     "params_crlf_syntax.json: malformed&&line 3",
     crlf('{\n  "method": "lsq",\n  "model": "base" x\n}\n'))
case("params_cr_syntax.json", "params", "params_cr_syntax.json: malformed&&line 3",
     '{\r  "method": "lsq",\r  "model": "base" x\r}\r')

# The cases docs/data-format.md names.
case("poses_semicolon.csv", "poses", "poses_semicolon.csv, line 1: missing column pose (the header is one column holding `;`",
     "pose;a;b;c;d_mm;d1_mm;d2_mm;d3_mm;d4_mm\n1;0;0;1;-30;40,5;40;40;40\n")
case("poses_no_three.csv", "poses",
     "poses_no_three.csv: no pose has three valid readings: a normal needs three",
     P + "1,0,0,1,-30,40,40,,\n2,0,0,1,-30,,NaN,40,40\n")
case("poses_degenerate_plane.csv", "poses",
     "poses_degenerate_plane.csv, line 3: degenerate plane normal: (a, b, c) has zero length",
     P + R1 + "2,0,0,0,-30,40,40,40,40\n")
case("poses_negative.csv", "poses",
     "poses_negative.csv, line 2: column d2_mm: negative distance -1",
     P + "1,0,0,1,-30,40,-1,40,40\n")
case("poses_infinite.csv", "poses",
     "poses_infinite.csv, line 2: column d3_mm: reading must be finite or empty, got 'inf'",
     P + "1,0,0,1,-30,40,40,inf,40\n")
case("poses_missing_column.csv", "poses",
     "poses_missing_column.csv, line 1: missing column d3_mm",
     "pose,a,b,c,d_mm,d1_mm,d2_mm,d4_mm\n1,0,0,1,-30,40,40,40\n")
case("poses_d0.csv", "poses",
     "poses_d0.csv, line 1: column d0_mm: sensors are numbered from 1",
     "pose,a,b,c,d_mm,d0_mm,d1_mm,d2_mm,d3_mm,d4_mm\n1,0,0,1,-30,1,40,40,40,40\n")
case("poses_five_sensors.csv", "poses",
     "poses_five_sensors.csv, line 1: column d5_mm: the head has only 4 sensors",
     "pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm,d5_mm\n1,0,0,1,-30,40,40,40,40,40\n")
case("poses_partial_sd.csv", "poses",
     "poses_partial_sd.csv, line 1: missing column s2_mm: give s1_mm … s4_mm together",
     "pose,a,b,c,d_mm,d1_mm,d2_mm,d3_mm,d4_mm,s1_mm\n1,0,0,1,-30,40,40,40,40,0.01\n")
case("poses_empty.csv", "poses", "poses_empty.csv: empty file: no header row", "# nothing\n\n")
case("poses_no_rows.csv", "poses", "poses_no_rows.csv: no pose rows", P)
case("poses_not_utf8.csv", "poses", "poses_not_utf8.csv, line 2: not valid UTF-8 text",
     None, P.encode() + b"1,0,0,1,-30,40,\xff\xfe,40,40\n")
case("sensors_zero_direction.csv", "sensors",
     "sensors_zero_direction.csv, line 2: beam direction (m, n, q) has zero length",
     S + "1,0,0,0,0,0,0\n")
case("sensors_gap.csv", "sensors",
     "sensors_gap.csv, line 3: sensors must be numbered 1..2 without gaps: sensor 2 is missing",
     S + "1,50,0,0,0,0,1\n3,0,50,0,0,0,1\n")
case("sensors_negative_sigma.csv", "sensors",
     "sensors_negative_sigma.csv, line 2: column sigma_mm: must be a non-negative number, got -0.01",
     "sensor,x_mm,y_mm,z_mm,m,n,q,sigma_mm\n1,50,0,0,0,0,1,-0.01\n")
case("sensors_bad_range.csv", "sensors",
     "sensors_bad_range.csv, line 2: range_max_mm 20 is not beyond range_min_mm 60",
     "sensor,x_mm,y_mm,z_mm,m,n,q,range_min_mm,range_max_mm\n1,50,0,0,-0.5,0,0.866,60,20\n")
case("sensors_bad_number.csv", "sensors",
     "sensors_bad_number.csv, line 3: column x_mm: 'abc' is not a valid number",
     S + "1,0,0,0,0,0,1\n2,abc,0,0,0,0,1\n")

# Plausibility (issue 31: units, impossible readings).
case("run_readings_inches.csv", "run",
     "run_readings_inches.csv: the readings d1_mm … d4_mm: these look like inches; write them in millimetres (inches × 25.4)",
     poses(reading_k=1 / 25.4))
case("run_readings_micrometres.csv", "run",
     "run_readings_micrometres.csv: the readings d1_mm … d4_mm: these look like micrometres; write them in millimetres (micrometres ÷ 1000)",
     poses(reading_k=1000))
case("run_planes_inches.csv", "run",
     "run_planes_inches.csv: the planes' d_mm: these look like inches; write them in millimetres (inches × 25.4)",
     poses(plane_k=1 / 25.4))
case("run_planes_micrometres.csv", "run",
     "run_planes_micrometres.csv: the planes' d_mm: these look like micrometres",
     poses(plane_k=1000))
case("run_one_reading_100x.csv", "run-left",
     "sensor 2, pose 3 (line 4): reading",
     poses(wild=(3, 2, 100)))
case("readings_300mm.csv", "readings-left",
     "sensor 2, pose 2 (line 3): reading 300 mm outside the sensor's range 0–",
     "pose,d1_mm,d2_mm,d3_mm,d4_mm\n1,41,41,41,41\n2,41,300,41,41\n3,40,41,42,41\n")
case("readings_micrometres.csv", "readings-left",
     "readings_micrometres.csv: 8 of 8 readings lie outside their sensor's measuring range",
     "pose,d1_mm,d2_mm,d3_mm,d4_mm\n1,41000,41000,41000,41000\n2,41500,41000,40000,41000\n")

with open(os.path.join(HERE, "cases.tsv"), "w") as f:
    f.write("# file\treader\tthe message must contain (file, line, cause)\n")
    for c in CASES:
        f.write("\t".join(c) + "\n")

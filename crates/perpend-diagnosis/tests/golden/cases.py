#!/usr/bin/env python3
"""Writes the blind runs of the diagnosis golden test (tests/diagnosis/diagnose_golden.rs).

Each case is one run of the independent generator host-tests/blind/gen.py
(its CASE.json parameters as score.py's `make_case` builds them, base regime,
effect size 2x the visible noise, 30 poses to keep the debug-build test
quick; the incidence run is larger: 6x, 60 poses, 15 deg, and still named
`none` on main at 7b3a831, one of issue 35's misses).
Run once from the repository root:

    python3 crates/perpend-diagnosis/tests/golden/cases.py

It rewrites crates/perpend-diagnosis/tests/golden/blind/<name>/{case.json,sensors.csv,poses.csv}
(truth.json is dropped: the test never reads it). Then bless the outputs:
PERPEND_BLESS=1 cargo test -p perpend-diagnosis --test diagnosis diagnose_golden.
"""

import json
import math
import os
import sys

ROOT = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(ROOT, "..", "..", "..", "..", "host-tests", "blind"))
import gen  # noqa: E402

BASE = {"sigma_mm": 0.01, "declared": 1.0, "tracker_factor": 1.0,
        "spread_deg": 5.0, "poses": 30}


def case(seed, geometry, effects=(), blunders=0, size=2.0, **over):
    c = dict(BASE)
    c.update(over)
    s = size * math.hypot(c["sigma_mm"], 0.0065 * c["tracker_factor"])
    c.update({"seed": seed, "geometry": geometry, "blunders": blunders,
              "shuffle": seed % 3 == 0,
              "effects": [[k, s] for k in effects]})
    return c


CASES = {
    "null": case(9101, "ring45"),
    "gain": case(9102, "tian30", ["gain"]),
    "incidence": case(9103, "ring45", ["incidence_tan"], size=6.0, spread_deg=15.0, poses=60),
    "ripple": case(9109, "ring45", ["ripple"], size=4.0),
    "thermal": case(9104, "tian30", ["thermal_lag"]),
    "drift": case(9105, "ring45", ["drift_settle"]),
    "blunder": case(9106, "tian30", blunders=2),
    "mixture": case(9107, "ring45", ["gain", "thermal_lag"]),
    "null_undeclared": case(9108, "tian30", declared=None),
}

if __name__ == "__main__":
    for name, c in CASES.items():
        out = os.path.join(ROOT, "blind", name)
        gen.write(c, out)
        os.remove(os.path.join(out, "truth.json"))
        with open(os.path.join(out, "case.json"), "w") as f:
            json.dump(c, f, indent=1, sort_keys=True)
            f.write("\n")

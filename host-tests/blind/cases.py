"""What score.py (the grid) and v3.py (issue 35's block) share: the base
regime, the effect names the diagnosis may answer for each true effect,
the visible noise of a case, and one case run through `perpend diagnose`.

A module of its own so that neither imports the other for it (score.py
only starts v3.py for `--v3`). Only the standard library is used.
"""

import json
import math
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import gen  # noqa: E402

BASE = {"sigma_mm": 0.01, "declared": 1.0, "tracker_factor": 1.0,
        "spread_deg": 5.0, "poses": 60}

# what a right answer names, per generated effect
ACCEPT = {
    # the linearity error has two forms: a polynomial and a spline table
    "gain": {"gain", "nonlinearity", "linearity_table"},
    "linearity_s": {"nonlinearity", "linearity_table"},
    "linearity_cubic": {"nonlinearity", "linearity_table"},
    "incidence_tan": {"incidence"},
    "incidence_sec": {"incidence"},
    "crosstalk": {"crosstalk"},
    # monotonic temperature: time-like effects, thermal and drift both fit
    "thermal_lag": {"thermal", "drift"},
    "drift_settle": {"drift", "thermal"},
    # off the catalogue: the physics each shape belongs to
    "linearity_knee": {"nonlinearity", "linearity_table"},
    "thermal_lag2": {"thermal", "drift"},
    "crosstalk_sq": {"crosstalk"},
    # issue 46 (power.py): gain on two sensors; a tracker whose planes
    # drift during the run (a time-like error common to the sensors)
    "gain2": {"gain", "nonlinearity", "linearity_table"},
    "tracker_drift": {"drift", "thermal"},
}


def noise_scale(case):
    """The visible noise of a reading [mm]: reading noise and the tracker's
    share at the spots (about 6.5 um at xi = 0.02 mm, 20 points, 150 mm)."""
    return math.hypot(case["sigma_mm"], 0.0065 * case["tracker_factor"])


def run_one(args):
    perpend, case = args
    with tempfile.TemporaryDirectory() as d:
        gen.write(case, d)
        p = subprocess.run(
            [perpend, "--quiet", "diagnose", "--sensors", os.path.join(d, "sensors.csv"),
             "--poses", os.path.join(d, "poses.csv"), "--json",
             # verdicts only: the detection limits of a `none` (issue 46
             # item 3) change no verdict and are checked by limits_check.py
             "--limit-draws", "0"],
            capture_output=True, text=True, timeout=120)
        with open(os.path.join(d, "truth.json")) as f:
            truth = json.load(f)
    if p.returncode != 0:
        return {"case": case, "error": p.stdout.strip() or p.stderr.strip()}
    return {"case": case, "out": json.loads(p.stdout), "truth": truth}

#!/usr/bin/env python3
"""The tracker-tilt estimate of `perpend frames` (issue 36) on reversal runs
written by gen.py, which shares no code with it (its own geometry, tracker
fit, turn convention and noise).

Two regimes, each with tilted runs (both tilts drawn uniform in +-0.1 deg)
and tilt-free runs:

* resolved (reading noise 4 um, tracker x0.5, +-10 deg, 96 poses at 0/90/
  180/270 deg): every estimate resolved; the truth within 3 sigma of the
  estimate (misses allowed: 1 per 20 estimates); on tilt-free runs
  "significant" (beyond 2 sigma) at most 3 per 20 estimates (5 % expected);
* noisy (10 um, tracker x1, +-5 deg, 48 poses): the tilt is not resolved
  and must be reported so (never a significant estimate, a warning naming
  the poses it would take).

Seeds 7000000 + k, never used to tune anything.

Usage: frames_check.py PERPEND [--runs N] (N tilted + N tilt-free runs per
regime, default 10). Exit 1 when a check fails.
"""

import json
import math
import os
import random
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import gen  # noqa: E402

REGIMES = {
    "resolved": {"sigma_mm": 0.004, "tracker_factor": 0.5, "spread_deg": 10.0, "poses": 96},
    "noisy": {"sigma_mm": 0.01, "tracker_factor": 1.0, "spread_deg": 5.0, "poses": 48},
}
SEED_BASE = 7000000


def case(regime, seed, tilted):
    rng = random.Random(seed)
    tilt = [rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)] if tilted else [0.0, 0.0]
    c = {"declared": 1.0, "seed": seed, "geometry": "ring45", "effects": [],
         "blunders": 0, "shuffle": False, "reversal": 4, "tracker_tilt_deg": tilt}
    c.update(REGIMES[regime])
    return c


def estimate(perpend, c):
    with tempfile.TemporaryDirectory() as d:
        gen.write(c, d)
        out = subprocess.run(
            [perpend, "frames", "--json", "--sensors", os.path.join(d, "sensors.csv"),
             "--poses", os.path.join(d, "poses.csv"), "--plan", os.path.join(d, "plan.csv")],
            capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit("perpend frames failed: " + out.stderr + out.stdout)
    return json.loads(out.stdout)


def tilts(rep):
    """The two tracker-tilt entries of a report."""
    return [e for e in rep["errors"] if e["name"].startswith("tracker tilt")]


def main(argv):
    perpend = argv[0]
    n = int(argv[argv.index("--runs") + 1]) if "--runs" in argv else 10
    fails = []
    counts = {"within1": 0, "within2": 0, "within3": 0, "tilted": 0, "sig_null": 0, "null": 0, "noisy_sig": 0,
              "noisy": 0, "unresolved_warned": 0}
    for k in range(n):
        for tilted in (True, False):
            seed = SEED_BASE + 2 * k + (0 if tilted else 1)
            c = case("resolved", seed, tilted)
            rep = estimate(perpend, c)
            for e, t in zip(tilts(rep), c["tracker_tilt_deg"]):
                if not e["resolved"]:
                    fails.append("resolved regime, seed %d: %s not resolved" % (seed, e["name"]))
                    continue
                if tilted:
                    counts["tilted"] += 1
                    truth = math.radians(t) * 1e6
                    for m in (1, 2, 3):
                        counts["within%d" % m] += abs(e["value"] - truth) <= m * e["sigma"]
                else:
                    counts["null"] += 1
                    counts["sig_null"] += e["significant"]
            c = case("noisy", seed, tilted)
            rep = estimate(perpend, c)
            for e in tilts(rep):
                counts["noisy"] += 1
                counts["noisy_sig"] += e["significant"]
            counts["unresolved_warned"] += sum(
                "not resolved although the head turned" in w for w in rep["warnings"])
    print("frames: resolved regime: truth within 1/2/3 sigma %d/%d/%d of %d; tilt-free "
          "significant %d/%d"
          % (counts["within1"], counts["within2"], counts["within3"], counts["tilted"],
             counts["sig_null"], counts["null"]))
    print("frames: noisy regime: significant %d/%d; warned not resolved %d/%d"
          % (counts["noisy_sig"], counts["noisy"], counts["unresolved_warned"], counts["noisy"]))
    if counts["tilted"] - counts["within3"] > max(1, counts["tilted"] // 20):
        fails.append("truth outside 3 sigma in %d of %d estimates"
                     % (counts["tilted"] - counts["within3"], counts["tilted"]))
    if counts["sig_null"] > max(1, (3 * counts["null"]) // 20):
        fails.append("tilt-free runs significant in %d of %d estimates"
                     % (counts["sig_null"], counts["null"]))
    if counts["noisy_sig"] > 0 or counts["unresolved_warned"] < counts["noisy"]:
        fails.append("noisy regime: a tilt was called significant or not warned as unresolved")
    for f in fails:
        print("frames: FAIL " + f)
    return 1 if fails else 0


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit("usage: frames_check.py PERPEND [--runs N]")
    sys.exit(main(sys.argv[1:]))

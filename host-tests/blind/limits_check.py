#!/usr/bin/env python3
"""Checks the detection limits that `perpend diagnose` states with a `none`
(`detection_limits` in its JSON, docs/diagnosis.md "Detection limits")
on runs of the independent generator gen.py (no code shared with perpend).

For each regime and seed: the effect-free draw (gen.py's case with no
effect) is diagnosed; where the verdict is `none`, each checked
candidate's stated limit is read. The same draw (same seed: same head,
poses, planes and noise) is then written again with gen.py's own version
of the effect at exactly that limit, and diagnosed: the effect counts as
found when the verdict names the candidate (`strict`) or what the blind
grid accepts for gen.py's effect (`accepted`, cases.ACCEPT). The claim
(issue 46 item 3): found in >= 85 % of the runs.

gen.py sizes an effect by its visible part; the limit is an amplitude. So
the effect is drawn once at a reference size, its amplitude read from the
coefficients gen.py drew (gen.rescale is wrapped to see them), and the
size scaled by limit / amplitude (gen.py's effects are linear in their
size below its physical caps; a run whose effect gen.py capped below the
limit is counted apart as `capped`). Amplitudes, in the limit's units:

| candidate       | gen.py effect  | amplitude compared with the limit                          |
|-----------------|----------------|------------------------------------------------------------|
| gain            | gain           | RMS over the sensors of g_i [%]; g (d - d_lo): same form (the offset is a zero point) |
| linearity_table | linearity_s    | RMS of A_i [um], peak of A sin(pi x) over the run (the limit's S is sin(pi u/s) about the mean) |
| incidence       | incidence_sec  | |k| (1/cos 30deg - 1) [um at 30deg]: same form, one k for all sensors (the limit's alternates signs) |
| crosstalk       | crosstalk      | c [%]; scan order drawn per case, half not the sensor order (the limit's: sensor order) |
| thermal         | thermal_lag    | RMS of k_i [um/C] on the lagged sensor temperature (the limit's: the lag chosen on the effect-free run) |
| drift           | drift_settle   | RMS of A_i (1 - e^(-T/tau)) / T [um/min], the mean rate over the run (the limit's: linear drift) |

Usage: limits_check.py --perpend BIN [--seeds 20] [--seed-base 700000]
       [--regime base --regime "spread 15 deg"] [--only gain,thermal] [--jobs 2]
Only the standard library is used.
"""

import argparse
import concurrent.futures as cf
import json
import math
import os
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import gen  # noqa: E402
from cases import ACCEPT, BASE, noise_scale  # noqa: E402

REGIMES = {
    "base": {},
    "spread 15 deg": {"spread_deg": 15.0},
    "30 poses": {"poses": 30},
}

# candidate -> gen.py effect
FORMS = {
    "gain": "gain",
    "linearity_table": "linearity_s",
    "incidence": "incidence_sec",
    "crosstalk": "crosstalk",
    "thermal": "thermal_lag",
    "drift": "drift_settle",
}


def rms(xs):
    return math.sqrt(sum(x * x for x in xs) / len(xs))


def amplitude(kind, par, run_s):
    """gen.py's coefficients of `kind` in the limit's units (table above)."""
    if kind == "gain":
        return 100.0 * rms(par["g"])
    if kind == "linearity_s":
        return 1000.0 * rms(par["A"])
    if kind == "incidence_sec":
        return 1000.0 * abs(par["k"]) * (1.0 / math.cos(math.radians(30.0)) - 1.0)
    if kind == "crosstalk":
        return 100.0 * par["c"]
    if kind == "thermal_lag":
        return 1000.0 * rms(par["k"])
    if kind == "drift_settle":
        rate = [a * (1.0 - math.exp(-run_s / par["tau"])) / run_s for a in par["A"]]
        return 60000.0 * rms(rate)
    raise ValueError(kind)


def drawn(case):
    """gen.generate(case) and the coefficients of its (single) effect after
    gen.py's scaling."""
    seen = []
    orig = gen.rescale

    def spy(kind, par, f):
        orig(kind, par, f)
        seen.append((kind, par))

    gen.rescale = spy
    try:
        out = gen.generate(case)
    finally:
        gen.rescale = orig
    return out, seen


def case_of(regime, seed, effects):
    case = dict(BASE)
    case.update(REGIMES[regime])
    case.update({"seed": seed, "geometry": ["ring45", "tian30"][seed % 2], "effects": effects,
                 "blunders": 0, "shuffle": seed % 3 == 0})
    return case


def diagnose(perpend, case):
    with tempfile.TemporaryDirectory() as d:
        gen.write(case, d)
        p = subprocess.run([perpend, "--quiet", "diagnose", "--sensors",
                            os.path.join(d, "sensors.csv"), "--poses",
                            os.path.join(d, "poses.csv"), "--json"],
                           capture_output=True, text=True, timeout=300)
    if p.returncode != 0:
        return {"error": p.stdout.strip() or p.stderr.strip()}
    return json.loads(p.stdout)


def at_limit(perpend, regime, seed, cand, limit):
    """The draw `seed` with gen.py's form of `cand` at amplitude `limit`,
    diagnosed: a result row."""
    kind = FORMS[cand]
    ref = noise_scale(case_of(regime, seed, [])) * 1.0
    (_, _, hidden), seen = drawn(case_of(regime, seed, [[kind, ref]]))
    a0 = amplitude(kind, seen[0][1], hidden["run_s"])
    size = ref * limit / a0
    case = case_of(regime, seed, [[kind, size]])
    (_, _, hidden), seen = drawn(case)
    a = amplitude(kind, seen[0][1], hidden["run_s"])
    row = {"regime": regime, "seed": seed, "candidate": cand, "limit": limit, "injected": a}
    if a < 0.98 * limit:
        row["capped"] = True
        return row
    out = diagnose(perpend, case)
    if "error" in out:
        row["error"] = out["error"]
        return row
    named = [e["effect"] for e in out["effects"]] if out["effect"] != "unexplained" else []
    row["verdict"] = out["effect"]
    row["named"] = named
    row["strict"] = cand in named
    row["accepted"] = bool(set(named) & ACCEPT[kind])
    return row


def one_seed(args):
    perpend, regime, seed, only = args
    out = diagnose(perpend, case_of(regime, seed, []))
    if "error" in out:
        return [{"regime": regime, "seed": seed, "error": out["error"]}]
    if out["effect"] != "none":
        return [{"regime": regime, "seed": seed, "null_verdict": out["effect"]}]
    rows = []
    for lim in out.get("detection_limits", []):
        cand = lim["effect"]
        if cand not in only:
            continue
        if lim["limit"] is None:
            rows.append({"regime": regime, "seed": seed, "candidate": cand,
                         "not_detectable": lim["reason"]})
            continue
        rows.append(at_limit(perpend, regime, seed, cand, lim["limit"]))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--perpend", required=True)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--seed-base", type=int, default=700000)
    ap.add_argument("--regime", action="append")
    ap.add_argument("--only", default=",".join(FORMS))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--rows", help="write every row as JSON lines here")
    a = ap.parse_args()
    regimes = a.regime or ["base", "spread 15 deg"]
    only = a.only.split(",")
    jobs = [(a.perpend, r, a.seed_base + k, only) for r in regimes for k in range(a.seeds)]
    # processes, not threads: drawn() wraps a function of the gen module
    with cf.ProcessPoolExecutor(max_workers=max(1, a.jobs)) as ex:
        rows = [x for rs in ex.map(one_seed, jobs) for x in rs]
    if a.rows:
        with open(a.rows, "w") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")
    nulls = [r for r in rows if "null_verdict" in r]
    print(f"effect-free draws not `none` (no limits stated): {len(nulls)}"
          + "".join(f"\n  {r['regime']} seed {r['seed']}: {r['null_verdict']}" for r in nulls))
    print("| regime | candidate (gen.py form) | stated limit, median (range) | found, strict | found, accepted | capped by gen.py | not detectable |")
    print("|---|---|---|---|---|---|---|")
    ok = True
    for reg in regimes:
        for cand in only:
            rs = [r for r in rows if r.get("regime") == reg and r.get("candidate") == cand]
            graded = [r for r in rs if "strict" in r]
            lims = sorted(r["limit"] for r in rs if "limit" in r)
            nd = [r for r in rs if "not_detectable" in r]
            cap = [r for r in rs if r.get("capped")]
            s = sum(r["strict"] for r in graded)
            acc = sum(r["accepted"] for r in graded)
            med = f"{lims[len(lims) // 2]:.3g} ({lims[0]:.3g}-{lims[-1]:.3g})" if lims else "-"
            n = len(graded)
            rate = f"{s}/{n} ({100.0 * s / n:.0f} %)" if n else "-"
            rate_a = f"{acc}/{n} ({100.0 * acc / n:.0f} %)" if n else "-"
            print(f"| {reg} | {cand} ({FORMS[cand]}) | {med} | {rate} | {rate_a} | {len(cap)} | {len(nd)} |")
            if n and acc < 0.85 * n:
                ok = False
    errors = [r for r in rows if "error" in r]
    for r in errors:
        print("error:", r)
    print("claim (found, accepted, >= 85 % in every cell):", "holds" if ok else "NOT MET")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""The diagnosis's power against the oracle (issue 46, item 1).

For every run written by gen.py, `perpend diagnose` answers from
sensors.csv and poses.csv, and oracle.py tests each injected effect's true
form (free amplitudes on all four sensors, not told which carry it) at the
diagnosis's per-candidate level alpha / m (alpha = 0.01, m its candidates:
0.01 / 7). Per effect class and size: the oracle's power (rejections), the
diagnosis's power (the right effect named: cases.ACCEPT, and the verdict
not `none` or `unexplained`, as score.py grades), their ratio; and per
regime, on effect-free draws, the false positives of both.

Classes (CLASSES): the catalogue's singles, and where its assumptions are
weakest (gen.py, issue 46): effects on one or two sensors only, a head
that is neither ring-symmetric nor of one cone angle (`skew`), forms the
candidates only approximate (incidence 1/cos - 1 at 6 um, a settling
drift under a warm-up), three effects at once, a tracker whose planes
drift during the run, a one-sensor gain among tracker blunders.
Sizes are score.py's: what the paper's model cannot absorb of the effect
(gen.py's visible RMS) in units of the visible noise, 0.25 to 4; each
cell also shows the median normal cost (gen.py `normal_cost`: the
calibrated normal's held-out error over the same-draw floor) and the
median visible size reached (PHYSICAL caps some below the size asked).

Effect-free draws: each class drawn at size 0 (its form drawn, its
amplitudes zero): `--nulls` per regime go through the diagnosis too (its
false positives, and the oracle's), `--oracle-nulls` per class through
the oracle only (its null rejection rate: the F reference checked on the
same statistic without the effect).

    power.py --perpend BIN [--quick] [--check] [--seed-base N] [--runs N]
             [--nulls N] [--oracle-nulls N] [--sizes 0.5,2] [--jobs N]
             [--only "NAME;NAME"] [--md FILE] [--json FILE] [--from-json FILE]

The goal (issue 46): diagnosis power >= 0.8x the oracle's wherever the
oracle's is >= 50 %, false positives <= 5 % per regime; every miss is
printed (`goal missed:`). `--check` exits 1 on CI's gates instead
(`ci_gates`: what holds today, with a margin, so that a regression fails;
the goal itself is not met today and is printed beside them). Only the
standard library is used; imports gen, oracle and cases.
"""

import argparse
import concurrent.futures as cf
import json
import math
import os
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import cases  # noqa: E402
import gen  # noqa: E402
import oracle  # noqa: E402

SEEDS = 4600000

# regime name -> factors changed from cases.BASE
REGIMES = {
    "base": {},
    "sigma 0.006 + spread 15": {"sigma_mm": 0.006, "spread_deg": 15.0},
    "sigma 0.03 + standoff 20": {"sigma_mm": 0.03, "standoff_range_mm": 20.0},
    "spread 15": {"spread_deg": 15.0},
    "base + 2 blunders": {"blunders": 2},
    "skew head": {"geometry": "skew"},
}

# class -> (regime, effects: [kind, n sensors or 0 for all])
CLASSES = [
    ("gain", "base", [["gain", 0]]),
    ("linearity_s", "base", [["linearity_s", 0]]),
    ("crosstalk", "base", [["crosstalk", 0]]),
    ("thermal_lag", "base", [["thermal_lag", 0]]),
    ("drift_settle under a warm-up", "base", [["drift_settle", 0]]),
    ("incidence 1/cos-1, 6 um", "sigma 0.006 + spread 15", [["incidence_sec", 0]]),
    ("gain on two sensors, 30 um", "sigma 0.03 + standoff 20", [["gain2", 0]]),
    ("linearity_s on one sensor", "base", [["linearity_s", 1]]),
    ("thermal_lag on one sensor", "base", [["thermal_lag", 1]]),
    ("gain on one sensor + blunders", "base + 2 blunders", [["gain", 1]]),
    ("three: gain + thermal_lag + incidence_sec", "spread 15",
     [["gain", 0], ["thermal_lag", 0], ["incidence_sec", 0]]),
    ("gain, skew head", "skew head", [["gain", 0]]),
    ("crosstalk, skew head", "skew head", [["crosstalk", 0]]),
    ("tracker drift (settling)", "base", [["tracker_drift", 0]]),
]

SIZES = (0.25, 0.5, 1.0, 2.0, 4.0)
QUICK_SIZES = (0.5, 2.0)

# the goal
GOAL_RATIO, GOAL_ORACLE, GOAL_FP = 0.8, 0.5, 0.05
# CI's gates (ci_gates): the pooled ratio (diagnosis named / oracle
# rejected, cells where the oracle's power >= 50 %) measured today, 0.91
# on the full run of docs/diagnosis.md ("Power against the oracle", with
# the nested test of issue 46 item 2; 0.73 before it) and 0.97 (30/31)
# on the quick form (seeds from SEEDS, deterministic; 0.77 before), less
# a margin of about 3 sd of the quick form's binomial spread at the full
# run's 0.91 (0.05 each): a regression fails it, the goal (0.8 per
# cell) is printed beside it
RATIO_FLOOR = 0.75


def make_case(cls, seed, size, j):
    """One run of class `cls` (a CLASSES entry) at `size` x the visible
    noise (0: effect-free, the forms still drawn)."""
    name, regime, effects = cls
    case = dict(cases.BASE)
    factors = dict(REGIMES[regime])
    geometry = factors.pop("geometry", ["ring45", "tian30"][j % 2])
    case.update(factors)
    case.update({"seed": seed, "geometry": geometry, "blunders": case.get("blunders", 0),
                 "shuffle": seed % 3 == 0, "normal_cost": size > 0})
    s = cases.noise_scale(case) * size
    case["effects"] = [[kind, s, n] if n else [kind, s] for kind, n in effects]
    return case


def plan(seed_base, sizes, n_runs, n_nulls, n_oracle_nulls):
    """Jobs: (class name, regime, size, case, diagnose?). Per regime
    `n_nulls` effect-free runs through both (cycling over the regime's
    classes' forms), per class `n_oracle_nulls` through the oracle only,
    per class and size `n_runs` through both."""
    jobs, seed = [], seed_base
    for regime in REGIMES:
        mine = [c for c in CLASSES if c[1] == regime]
        for j in range(n_nulls if mine else 0):
            seed += 1
            c = mine[j % len(mine)]
            jobs.append((c[0], regime, 0.0, make_case(c, seed, 0.0, j), True))
    for c in CLASSES:
        for j in range(n_oracle_nulls):
            seed += 1
            jobs.append((c[0], c[1], 0.0, make_case(c, seed, 0.0, j), False))
    for c in CLASSES:
        for size in sizes:
            for j in range(n_runs):
                seed += 1
                jobs.append((c[0], c[1], size, make_case(c, seed, size, j + seed), True))
    return jobs


def diagnose(perpend, generated, case):
    """`perpend diagnose --json` on the run: its answer, or {"error"}."""
    with tempfile.TemporaryDirectory() as d:
        gen.write(case, d, generated)
        p = subprocess.run(
            [perpend, "--quiet", "diagnose", "--sensors", os.path.join(d, "sensors.csv"),
             "--poses", os.path.join(d, "poses.csv"), "--json",
             # verdicts only: the detection limits of a `none` (issue 46
             # item 3) change no verdict and are checked by limits_check.py
             "--limit-draws", "0"],
            capture_output=True, text=True, timeout=300)
    if p.returncode != 0:
        return {"error": (p.stdout.strip() or p.stderr.strip())[:300]}
    return json.loads(p.stdout)


def run_job(args):
    """One job: the run generated, the oracle's p per effect, and the
    diagnosis's answer in a few words (when the job asks for it)."""
    perpend, (name, regime, size, case, with_diag) = args
    nominal, rows, hidden, state = gen.generate_full(case)
    tests = oracle.judge_run(state, rows)
    row = {"class": name, "regime": regime, "size": size, "seed": case["seed"],
           "kinds": [k for k, _ in state["effects"]], "p": [t["p"] for t in tests],
           "visible": [v / cases.noise_scale(case) for v in hidden["visible_rms_mm"]],
           "normal_cost": hidden.get("normal_cost")}
    if with_diag:
        out = diagnose(perpend, (nominal, rows, hidden), case)
        if "error" in out:
            row["error"] = out["error"]
        else:
            row["effect"] = out.get("effect")
            row["named"] = [e["effect"] for e in out.get("effects", [])]
            row["m"] = len([c for c in out.get("candidates", []) if c.get("effect") != "none"])
    return row


def judged(row):
    """Per effect of the run: (oracle rejected, diagnosis named it), and
    whether the diagnosis named an effect none of the true ones accepts."""
    level = oracle.candidate_level(row.get("m") or oracle.CANDIDATES)
    said = row.get("effect") not in (None, "none", "unexplained")
    named = set(row.get("named", []))
    allowed = set().union(*[cases.ACCEPT[k] for k in row["kinds"]]) if row["kinds"] else set()
    per = [(p < level, said and bool(cases.ACCEPT[k] & named)) for k, p in zip(row["kinds"], row["p"])]
    return per, bool(named - allowed)


def summarise(rows):
    """Cells (class, effect, size) and regimes' null counts."""
    cells, nulls = {}, {}
    for r in rows:
        if r["size"] == 0:
            n = nulls.setdefault(r["regime"], {"diag": 0, "fp": 0, "errors": 0, "oracle": 0,
                                               "oracle_rej": 0, "oracle_rej05": 0, "said": {}})
            level = oracle.candidate_level(r.get("m") or oracle.CANDIDATES)
            for p in r["p"]:
                n["oracle"] += 1
                n["oracle_rej"] += int(p < level)
                n["oracle_rej05"] += int(p < 0.05)
            if "effect" in r or "error" in r:
                n["diag"] += 1
                if "error" in r:
                    n["errors"] += 1
                elif r["effect"] != "none":
                    n["fp"] += 1
                    w = "+".join(r["named"]) or r["effect"]
                    n["said"][w] = n["said"].get(w, 0) + 1
            continue
        per, wrong = judged(r)
        multi = len(r["kinds"]) > 1
        for j, (o, d) in enumerate(per):
            key = (r["class"], r["kinds"][j] if multi else "", r["size"])
            c = cells.setdefault(key, {"regime": r["regime"], "n": 0, "oracle": 0, "diag": 0,
                                       "wrong": 0, "errors": 0, "cost": [], "visible": []})
            c["n"] += 1
            c["oracle"] += int(o)
            c["diag"] += int(d and "error" not in r)
            c["errors"] += int("error" in r)
            c["wrong"] += int(wrong)
            if r.get("normal_cost") is not None:
                c["cost"].append(r["normal_cost"])
            c["visible"].append(r["visible"][j])
    return cells, nulls


def median(xs):
    xs = sorted(xs)
    return xs[len(xs) // 2] if xs else float("nan")


def ratio(c):
    """Diagnosis power over the oracle's (None when the oracle has none)."""
    return c["diag"] / c["oracle"] if c["oracle"] else None


def markdown(cells, nulls):
    lines = ["| class | effect | regime | size (× visible noise) | visible reached (median) | normal cost (median × floor) | runs | oracle power | diagnosis power | ratio | wrong effect also named |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for (name, eff, size), c in cells.items():
        r = ratio(c)
        mark = ""
        if c["oracle"] / c["n"] >= GOAL_ORACLE and (r is None or r < GOAL_RATIO):
            mark = " (goal missed)"
        lines.append("| %s | %s | %s | %.2f | %.2f | %s | %d | %.2f | %.2f | %s%s | %d |" % (
            name, eff or "–", c["regime"], size, median(c["visible"]),
            "%.2f" % median(c["cost"]) if c["cost"] else "–", c["n"], c["oracle"] / c["n"],
            c["diag"] / c["n"], "–" if r is None else "%.2f" % r, mark, c["wrong"]))
    lines += ["", "| regime | effect-free runs diagnosed | diagnosis false positives | said | oracle null tests | oracle rejections at α/m | at 0.05 |",
              "|---|---|---|---|---|---|---|"]
    for reg, n in nulls.items():
        said = ", ".join("%s %d" % kv for kv in sorted(n["said"].items()))
        lines.append("| %s | %d | %d | %s | %d | %d | %d |" % (
            reg, n["diag"], n["fp"], said or "–", n["oracle"], n["oracle_rej"], n["oracle_rej05"]))
    return "\n".join(lines)


def compact(cells):
    """One row per class (and effect, in a run of several), one column per
    size: oracle power / diagnosis power, the goal's misses starred; the
    ratio pooled over the sizes where the oracle's power is >= 50 %
    (named / rejected); the median normal cost over the sizes >= 1."""
    sizes = sorted({k[2] for k in cells})
    rows = {}
    for (name, eff, size), c in cells.items():
        rows.setdefault((name, eff), {})[size] = c
    lines = ["| class (effect) | regime | " + " | ".join("%.2g×" % s for s in sizes)
             + " | ratio where the oracle ≥ 50 % (pooled) | normal cost at ≥ 1× (median) |",
             "|---|---|" + "---|" * len(sizes) + "---|---|"]
    for (name, eff), by in rows.items():
        cols = []
        for s in sizes:
            c = by.get(s)
            if not c:
                cols.append("–")
                continue
            miss = c["oracle"] / c["n"] >= GOAL_ORACLE and (ratio(c) or 0.0) < GOAL_RATIO
            cols.append("%.2f / %.2f%s" % (c["oracle"] / c["n"], c["diag"] / c["n"], " *" if miss else ""))
        costs = [x for s, c in by.items() if s >= 1.0 for x in c["cost"]]
        reg = next(iter(by.values()))["regime"]
        strong = [c for c in by.values() if c["oracle"] / c["n"] >= GOAL_ORACLE]
        d, o = sum(c["diag"] for c in strong), sum(c["oracle"] for c in strong)
        lines.append("| %s%s | %s | %s | %s | %s |" % (
            name, " (%s)" % eff if eff else "", reg, " | ".join(cols),
            "%.2f (%d/%d)" % (d / o, d, o) if o else "–", "%.2f" % median(costs) if costs else "–"))
    return "\n".join(lines)


def pooled(cells, nulls):
    """Pooled figures: the ratio over cells where the oracle's power is
    >= 50 % (named / rejected), false positives, the oracle's null
    rejections at alpha / m and at 0.05, and its power at sizes >= 2."""
    strong = [c for c in cells.values() if c["oracle"] / c["n"] >= GOAL_ORACLE]
    diag, orc = sum(c["diag"] for c in strong), sum(c["oracle"] for c in strong)
    big = [c for (_, _, size), c in cells.items() if size >= 2.0]
    return {"ratio": diag / orc if orc else None, "diag": diag, "oracle": orc,
            "fp": sum(n["fp"] for n in nulls.values()), "diag_nulls": sum(n["diag"] for n in nulls.values()),
            "null_tests": sum(n["oracle"] for n in nulls.values()),
            "null_rej": sum(n["oracle_rej"] for n in nulls.values()),
            "null_rej05": sum(n["oracle_rej05"] for n in nulls.values()),
            "big_n": sum(c["n"] for c in big), "big_oracle": sum(c["oracle"] for c in big),
            "errors": sum(c["errors"] for c in cells.values()) + sum(n["errors"] for n in nulls.values())}


def goal_misses(cells, nulls):
    """The issue's goal, cell by cell and regime by regime: (cells
    missed, regimes missed)."""
    out, fps = [], []
    for (name, eff, size), c in cells.items():
        if c["oracle"] / c["n"] >= GOAL_ORACLE:
            r = ratio(c)
            if r is None or r < GOAL_RATIO:
                out.append("%s%s at %.2f: diagnosis %d/%d, oracle %d/%d (ratio %.2f < %.1f)" % (
                    name, " (%s)" % eff if eff else "", size, c["diag"], c["n"], c["oracle"], c["n"],
                    r or 0.0, GOAL_RATIO))
    for reg, n in nulls.items():
        if n["diag"] and n["fp"] / n["diag"] > GOAL_FP:
            fps.append("%s: diagnosis false positives %d/%d (> 5 %%)" % (reg, n["fp"], n["diag"]))
    return out, fps


def ci_gates(p):
    """What CI holds today (each can fail): the oracle's null rejections
    at 0.05 within 0-2.5x the level (its F reference is calibrated) and at
    alpha / m no more than 3 (of a few dozen tests); its power at sizes
    >= 2 at least 80 % (it sees effects); the diagnosis's false positives
    pooled <= 5 %; the pooled ratio (diagnosis named / oracle rejected
    where the oracle's power >= 50 %) >= RATIO_FLOOR; no run in error."""
    fails = []
    if p["null_tests"] and p["null_rej05"] > max(2, 2.5 * 0.05 * p["null_tests"]):
        fails.append("oracle null rejections at 0.05: %d/%d (> 2.5x the level)" % (
            p["null_rej05"], p["null_tests"]))
    if p["null_rej"] > 3:
        fails.append("oracle null rejections at alpha/m: %d/%d (> 3)" % (p["null_rej"], p["null_tests"]))
    if p["big_n"] and p["big_oracle"] / p["big_n"] < 0.8:
        fails.append("oracle power at sizes >= 2: %d/%d (< 80 %%)" % (p["big_oracle"], p["big_n"]))
    if p["diag_nulls"] and p["fp"] / p["diag_nulls"] > GOAL_FP:
        fails.append("diagnosis false positives %d/%d pooled (> 5 %%)" % (p["fp"], p["diag_nulls"]))
    if p["ratio"] is not None and p["ratio"] < RATIO_FLOOR:
        fails.append("pooled power ratio %.2f (< floor %.2f)" % (p["ratio"], RATIO_FLOOR))
    if p["errors"]:
        fails.append("%d runs ended in an error" % p["errors"])
    return fails


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--perpend", required=True)
    ap.add_argument("--quick", action="store_true",
                    help="CI's form: sizes 0.5 and 2, one run a cell, 2 effect-free runs per regime, 3 oracle-only a class")
    ap.add_argument("--check", action="store_true", help="exit 1 when a CI gate fails (ci_gates)")
    ap.add_argument("--seed-base", type=int, default=SEEDS)
    ap.add_argument("--runs", type=int, help="runs per class and size (default 5; --quick 1)")
    ap.add_argument("--nulls", type=int, help="effect-free runs per regime, diagnosed (default 20; --quick 2)")
    ap.add_argument("--oracle-nulls", type=int,
                    help="effect-free draws per class, oracle only (default 40; --quick 3)")
    ap.add_argument("--sizes", help="comma-separated sizes (× visible noise; default 0.25,0.5,1,2,4)")
    ap.add_argument("--only", help="semicolon-separated class names (a subset of CLASSES; names hold commas)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--md", help="also write the tables here")
    ap.add_argument("--json", help="write one JSON line per run here")
    ap.add_argument("--from-json", help="summarise a --json file instead of running")
    a = ap.parse_args(argv)
    sizes = (tuple(float(x) for x in a.sizes.split(",")) if a.sizes
             else QUICK_SIZES if a.quick else SIZES)
    n_runs = a.runs if a.runs is not None else (1 if a.quick else 5)
    n_nulls = a.nulls if a.nulls is not None else (2 if a.quick else 20)
    n_onulls = a.oracle_nulls if a.oracle_nulls is not None else (3 if a.quick else 40)
    jobs = plan(a.seed_base, sizes, n_runs, n_nulls, n_onulls)
    if a.only:
        keep = set(x.strip() for x in a.only.split(";"))
        jobs = [j for j in jobs if j[0] in keep]
    t0 = time.time()
    if a.from_json:
        with open(a.from_json) as f:
            rows = [json.loads(line) for line in f]
    else:
        with cf.ThreadPoolExecutor(max(1, a.jobs)) as ex:
            rows = list(ex.map(run_job, [(a.perpend, j) for j in jobs]))
    if a.json and not a.from_json:
        with open(a.json, "w") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")
    cells, nulls = summarise(rows)
    md = compact(cells) + "\n\n" + markdown(cells, nulls)
    print(md)
    if a.md:
        with open(a.md, "w") as f:
            f.write(md + "\n")
    p = pooled(cells, nulls)
    misses, fp_misses = goal_misses(cells, nulls)
    for m in misses + fp_misses:
        print("  goal missed: " + m)
    fails = ci_gates(p)
    for f in fails:
        print("  gate failed: " + f)
    print("oracle comparison: %d runs in %.0f s; pooled ratio %s (goal >= %.1f where the oracle's power "
          ">= 50 %%; CI floor %.2f), %d of %d cells miss the goal; diagnosis false positives %d/%d "
          "(%d regimes > 5 %%); "
          "oracle null rejections %d/%d at alpha/m, %d at 0.05; %d gates failed" % (
              len(rows), time.time() - t0, "–" if p["ratio"] is None else "%.2f (%d/%d)" % (
                  p["ratio"], p["diag"], p["oracle"]),
              GOAL_RATIO, RATIO_FLOOR, len(misses), len(cells), p["fp"],
              p["diag_nulls"], len(fp_misses), p["null_rej"], p["null_tests"], p["null_rej05"], len(fails)))
    return 1 if a.check and fails else 0


if __name__ == "__main__":
    sys.exit(main())

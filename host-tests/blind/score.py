#!/usr/bin/env python3
"""Scores `perpend diagnose` on runs written by the independent generator
gen.py (which shares no code with perpend), over a grid of regimes.

Each cell of the grid is one regime (reading noise, declared noise, tracker
noise, pose spread, pose count, head geometry) and one class of truth
(nothing, a single effect, a pair, tracker blunders). The diagnosis sees
only sensors.csv and poses.csv; the truth is read after it answered.

    score.py --perpend target/release/perpend [--quick] [--json OUT] [--md OUT]
             [--check] [--seed-base N] [--nulls N] [--only TRUTHS]
             [--regime NAMES] [--runs OUT.jsonl]
    score.py --v3 --perpend BIN [v3.py's options]

`--v3` runs the v3 block instead (v3.py: the cases of issue 35, scored by
their cost to the calibrated normal; not in the reduced grid CI checks).

Seeds: the diagnosis was tuned on the default range (from 1000); the
figures of docs/diagnosis.md come from --seed-base 500000, never used for
tuning, with --nulls 200 effect-free runs per regime (enough to bound a 5 %
false-positive rate per cell). --quick runs a reduced grid (CI); --check exits 1 when a goal is missed:
false positives <= 5 % per regime, singles named >= 90 %, pairs both named
>= 80 %, blunders found >= 95 %, extended held-out RMS <= 1.15x the
same-draw floor where effects are named, over the least cost of estimating
the named model's extra coefficients (`estimation_cost`: 1.02-1.06 at 30
poses, less with more; the table shows the ratio with and without it). The same-draw floor is gen.py's
`oracle_heldout_mm`: what a calibration that knew the effects exactly
achieves on these very readings, held out by k-fold cross-validation as
the diagnosis holds out (the guide's "noise floor": perfect calibration on
the same draws). The diagnosis's own `expected_rms_mm` (its estimate of
that floor, from its noise estimate) is shown beside it. Only the standard library is used.
"""

import argparse
import concurrent.futures as cf
import json
import math
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import gen  # noqa: E402
from cases import ACCEPT, BASE, noise_scale, run_one  # noqa: E402,F401

# one factor at a time around the base regime
REGIMES = [
    ("base", {}),
    ("sigma 0.002", {"sigma_mm": 0.002}),
    ("sigma 0.03", {"sigma_mm": 0.03}),
    ("sigma 0.05", {"sigma_mm": 0.05}),
    ("declared x0.5", {"declared": 0.5}),
    ("declared x2", {"declared": 2.0}),
    ("declared missing", {"declared": None}),
    ("sample columns", {"n_samples": 16}),
    ("tracker x3", {"tracker_factor": 3.0}),
    ("spread 2 deg", {"spread_deg": 2.0}),
    ("spread 15 deg", {"spread_deg": 15.0}),
    ("30 poses", {"poses": 30}),
    ("120 poses", {"poses": 120}),
]

# Two factors at once (`--combined`): regimes off the grid, to check that
# what holds one factor at a time still holds where they meet.
COMBINED = [
    ("tracker x4", {"tracker_factor": 4.0}),
    ("tracker x3 + 30 poses", {"tracker_factor": 3.0, "poses": 30}),
    ("tracker x3 + spread 2", {"tracker_factor": 3.0, "spread_deg": 2.0}),
    ("sigma 0.03 + tracker x3", {"sigma_mm": 0.03, "tracker_factor": 3.0}),
    ("declared x0.5 + tracker x3", {"declared": 0.5, "tracker_factor": 3.0}),
    ("spread 2 + 30 poses", {"spread_deg": 2.0, "poses": 30}),
]

# Off the catalogue (`--offcat`): noise that is not Gaussian or not the same
# across the range, readings missing, single readings spattered, and three
# effect shapes neither gen.py's singles nor the diagnosis's candidates have
# (gen.py's docstring), with the usual singles beside them.
OFFCAT = [
    ("base", {}),
    ("noise t3", {"noise": "t3"}),
    ("noise hetero", {"noise": "hetero"}),
    ("missing readings", {"missing": 6}),
]
OFFCAT_SINGLES = ["linearity_knee", "thermal_lag2", "crosstalk_sq"]

SINGLES = ["gain", "linearity_s", "linearity_cubic", "incidence_tan", "incidence_sec",
           "crosstalk", "thermal_lag", "drift_settle"]
PAIRS = [("gain", "thermal_lag"), ("gain", "drift_settle"), ("crosstalk", "gain"),
         ("incidence_tan", "gain")]

# An effect is graded when what the paper's model cannot absorb of it is at
# least this many times the visible noise (the 50 % detection limit of the
# base regime is about 0.5: see the limit rows); a smaller one, capped by
# the physical bounds of gen.py, is reported as `small`, not graded.
VISIBLE_MIN = 1.0


def make_case(regime, truth, seed, size_sigma, geometry):
    case = dict(BASE)
    case.update(regime[1])
    case.update({"seed": seed, "geometry": geometry, "effects": [], "blunders": 0,
                 "shuffle": seed % 3 == 0})
    s = noise_scale(case) * size_sigma
    if truth == "none":
        pass
    elif truth == "blunders":
        case["blunders"] = 2
    elif truth == "spatter":
        case["spatter"] = 2
    elif truth == "ripple":
        case["effects"] = [["ripple", s]]
    elif isinstance(truth, tuple):
        case["effects"] = [[truth[0], s], [truth[1], s]]
    else:
        case["effects"] = [[truth, s]]
    return case


def same_draw_residuals(r):
    """gen.py's `oracle_heldout_mm` (zero points and directions fitted by
    k-fold cross-validation, k as the diagnosis chooses it, to the readings
    with the true effects removed) on the poses the diagnosis kept."""
    res = r["truth"].get("oracle_heldout_mm")
    if not res:
        return []
    out = {o["pose"] for o in r["out"].get("outlier_poses", [])}
    return [x for k, row in enumerate(res) if k + 1 not in out for x in row if x is not None]


def same_draw_floor(r):
    """The noise floor on the same draws, held out: RMS of
    `same_draw_residuals`."""
    xs = same_draw_residuals(r)
    return math.sqrt(sum(x * x for x in xs) / len(xs)) if xs else 0.0


def estimation_cost(r, named):
    """What estimating the named model's extra coefficients adds, at least,
    to the held-out RMS over the same-draw floor (which fits only the paper's
    5 per sensor): for least squares with p coefficients trained on n'
    readings, the held-out mean square is sigma^2 (1 + p/n') (fixed design,
    independent noise), so the named model's floor is the same-draw floor
    times sqrt((1 + p_e/n') / (1 + p_0/n')), n' = n (k-1)/k for k folds of
    n readings; p_0 and p_e from the diagnosis's `n_params` (a pair's
    extras add). A lower bound, and the goal divides by it: the effect-free
    runs of overhead.py measure about twice it (docs/diagnosis.md). 1.0
    where the counts are not in the answer."""
    out = r["out"]
    params = {c["effect"]: c.get("n_params") for c in out.get("candidates", [])}
    p0 = params.get("none")
    n = len(same_draw_residuals(r))
    k = out.get("folds") or 0
    if not p0 or not n or k < 2 or any(not params.get(e) for e in named):
        return 1.0
    pe = p0 + sum(params[e] - p0 for e in named)
    n_train = n * (k - 1) / k
    return math.sqrt((1 + pe / n_train) / (1 + p0 / n_train))


def grade(r):
    """Whether the answer is right, per class."""
    case = r["case"]
    if "error" in r:
        return {"ok": False, "why": "error: " + r["error"][:200]}
    out = r["out"]
    named = [e["effect"] for e in out.get("effects", [])]
    effect = out["effect"]
    g = {"effect": effect, "named": named}
    same = same_draw_floor(r)
    if same > 0 and out.get("expected_rms_mm", 0) > 0:
        # how well the diagnosis knows the floor it reports
        g["floor_same"] = out["expected_rms_mm"] / same
    kinds = [k for k, _ in case["effects"]]
    if not kinds:
        g["ok"] = effect == "none"
        if case["blunders"] or case.get("spatter"):
            found = {o["pose"] for o in out.get("outlier_poses", [])}
            want = set(r["truth"]["blunder_poses"]) | set(r["truth"].get("spatter_poses", []))
            g["blunders_found"] = want <= found
            g["extra_outliers"] = len(found - want)
        else:
            g["extra_outliers"] = len(out.get("outlier_poses", []))
        return g
    if kinds == ["ripple"]:
        g["ok"] = effect == "unexplained"
        return g
    hit = [bool(ACCEPT[k] & set(named)) for k in kinds]
    if len(kinds) == 2 and ACCEPT[kinds[0]] & ACCEPT[kinds[1]]:
        hit = [len(named) >= 2 and all(hit)]
    g["ok"] = all(hit) and effect not in ("none", "unexplained")
    g["partial"] = any(hit)
    # what the paper's model cannot absorb, in units of the visible noise
    g["visible"] = min(r["truth"]["visible_rms_mm"]) / noise_scale(case)
    # the extended model's held-out RMS against the floor, where effects are named
    ext = out["extended"]["heldout_rms_mm"]
    floor = out["expected_rms_mm"]
    if same > 0:
        g["base_same"] = out["base"]["heldout_rms_mm"] / same
        g["ext_same"] = ext / same
        if effect not in ("none", "unexplained"):
            g["ext_same_adj"] = g["ext_same"] / estimation_cost(r, named)
    if effect not in ("none", "unexplained") and floor > 0:
        g["rms_ratio"] = ext / floor
        # against the named model's own floor (its held-out RMS on
        # effect-free re-simulations), where one effect is named
        own = [c.get("expected_rms_mm", 0.0) for c in out["candidates"] if c["effect"] == effect]
        if len(named) == 1 and own and own[0] > 0:
            g["own_ratio"] = ext / own[0]
    return g


# Seed ranges: the diagnosis was tuned on runs from seed 1000 up (the
# default, and what CI runs); the figures of docs/diagnosis.md are reported
# from a range it was never tuned on (--seed-base 500000).
TUNE_SEEDS = 1000


def plan(quick, seed_base=TUNE_SEEDS, nulls=None, effects=None, combined=False, offcat=False):
    if offcat:
        return plan_offcat(seed_base, nulls if nulls is not None else 20,
                           effects if effects is not None else 3)
    # CI's reduced grid: the base and six regimes (the whole grid, `--full`,
    # runs every regime), 8 nulls and 2 effects of each kind a regime.
    regimes = REGIMES[:1] + [r for r in REGIMES[1:] if not quick or r[0] in (
        "sigma 0.03", "declared x0.5", "declared missing", "tracker x3", "spread 2 deg", "30 poses")]
    if combined:
        regimes = REGIMES[:1] + COMBINED
    n_null = nulls if nulls is not None else (8 if quick else 20)
    n_eff = effects if effects is not None else (2 if quick else 5)
    jobs, seed = regime_jobs(regimes, SINGLES + PAIRS + ["blunders", "ripple"], n_null, n_eff, seed_base)
    if not quick and not combined:
        # detection limit: base regime, sizes in units of the visible noise
        for size in (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0):
            for j in range(6):
                for truth in SINGLES:
                    seed += 1
                    jobs.append(("limit %.1f" % size, truth,
                                 make_case(REGIMES[0], truth, seed, size, ["ring45", "tian30"][j % 2])))
    return jobs


def summarise(results):
    cells = {}
    for reg, truth, r in results:
        g = grade(r)
        cls = ("none" if truth == "none" else "blunders" if truth in ("blunders", "spatter")
               else "ripple" if truth == "ripple" else "pair" if isinstance(truth, tuple) else "single")
        if cls in ("single", "pair") and g.get("visible", 1.0) < VISIBLE_MIN:
            # physically capped below reach: reported, not graded
            cls = "small " + cls
        if reg.startswith("limit") and "visible" in g:
            v = g["visible"]
            reg = "limit %.2f" % min((0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0), key=lambda b: abs(math.log(max(v, 1e-3) / b)))
        c = cells.setdefault(reg, {})
        k = c.setdefault(cls, {"n": 0, "ok": 0, "found": 0, "rms_max": 0.0, "own_max": 0.0,
                               "same_max": 0.0, "adj_max": 0.0, "wrong": []})
        if g.get("own_ratio"):
            k["own_max"] = max(k["own_max"], g["own_ratio"])
        k["n"] += 1
        k["ok"] += int(g.get("ok", False))
        # the floor the tool reports, where its noise model holds (not on the
        # out-of-catalogue ripple, nor where it answered `unexplained`)
        if g.get("floor_same") and truth != "ripple" and g.get("effect") != "unexplained":
            c.setdefault("_floor", {"ratios": []})["ratios"].append(g["floor_same"])
        if cls == "blunders":
            k["found"] += int(g.get("blunders_found", False))
        if g.get("rms_ratio"):
            k["rms_max"] = max(k["rms_max"], g["rms_ratio"])
            k["same_max"] = max(k["same_max"], g.get("ext_same", 0.0))
            k["adj_max"] = max(k["adj_max"], g.get("ext_same_adj", 0.0))
        if not g.get("ok", False):
            t = truth if isinstance(truth, str) else "+".join(truth)
            k["wrong"].append("%s (seed %d) -> %s %s" % (t, r["case"]["seed"], g.get("effect"),
                                                        g.get("named", g.get("why", ""))))
    return cells


def pooled_check(cells):
    """The CI gates on the reduced grid, pooled over its regimes (eight
    null runs per regime cannot resolve 5 % per cell): false positives
    <= 5 %, blunders found >= 90 %, ripple unexplained >= 75 %, graded
    singles named >= 80 %, graded pairs both named >= 75 %, no run that
    errors."""
    tot = {}
    for reg, c in cells.items():
        for cls, k in c.items():
            if cls.startswith("_"):
                continue
            t = tot.setdefault(cls, {"n": 0, "ok": 0, "found": 0})
            for x in ("n", "ok", "found"):
                t[x] += k.get(x, 0)
    fails = []

    def rate(cls, key="ok"):
        t = tot.get(cls)
        return None if not t or not t["n"] else t[key] / t["n"]

    if rate("none") is not None and rate("none") < 0.95:
        fails.append("false positives %.1f %% (> 5 %%)" % (100 * (1 - rate("none"))))
    if rate("blunders", "found") is not None and rate("blunders", "found") < 0.90:
        fails.append("blunders found %.0f %% (< 90 %%)" % (100 * rate("blunders", "found")))
    if rate("ripple") is not None and rate("ripple") < 0.75:
        fails.append("ripple unexplained %.0f %% (< 75 %%)" % (100 * rate("ripple")))
    if rate("pair") is not None and tot["pair"]["n"] >= 4 and rate("pair") < 0.75:
        fails.append("graded pairs both named %.0f %% (< 75 %%)" % (100 * rate("pair")))
    if rate("single") is not None and rate("single") < 0.80:
        fails.append("graded singles named %.0f %% (< 80 %%)" % (100 * rate("single")))
    summary = ", ".join("%s %d/%d" % (cls, t["ok"], t["n"]) for cls, t in sorted(tot.items()))
    return fails, summary


def check(cells):
    fails = []
    for reg, c in cells.items():
        if reg.startswith("limit"):
            continue
        for cls, k in c.items():
            if cls.startswith("_"):
                continue
            rate = k["ok"] / k["n"]
            if cls == "none" and rate < 0.95:
                fails.append("%s: false positives %.0f %% (> 5 %%)" % (reg, 100 * (1 - rate)))
            if cls == "single" and rate < 0.90:
                fails.append("%s: singles named %.0f %% (< 90 %%)" % (reg, 100 * rate))
            if cls == "pair" and rate < 0.80:
                fails.append("%s: pairs both named %.0f %% (< 80 %%)" % (reg, 100 * rate))
            if cls == "blunders" and k["found"] / k["n"] < 0.95:
                fails.append("%s: blunders found %.0f %% (< 95 %%)" % (reg, 100 * k["found"] / k["n"]))
            if cls in ("single", "pair") and k["adj_max"] > 1.15:
                fails.append("%s: %s extended RMS %.2fx the same-draw floor, %.2fx over the estimation cost (> 1.15)"
                             % (reg, cls, k["same_max"], k["adj_max"]))
    return fails


def json_grid(cells):
    """The cells as JSON: regime -> class -> counts, with each class's rate
    (`ok`/`n`: for `none` one minus the false-positive rate, for `single`
    the named rate, for `pair` the both-named rate) and, for blunders, the
    rate found; `_floor` holds the ratios of the tool's floor to the
    same-draw floor, one per run where its noise model holds."""
    grid = {}
    for reg, c in cells.items():
        g = grid.setdefault(reg, {})
        for cls, k in c.items():
            x = dict(k)
            if k.get("n"):
                x["rate"] = k["ok"] / k["n"]
                if cls == "none":
                    x["false_positive_rate"] = 1 - x["rate"]
                if cls == "blunders":
                    x["found_rate"] = k["found"] / k["n"]
            g[cls] = x
    return grid


def markdown(cells):
    lines = ["| regime | false positives (none) | singles named | pairs both named | blunders found (verdict none) | ripple unexplained | max ext. RMS / same-draw floor (÷ estimation cost) | max ext. RMS / diagnosis's floor | diagnosis's floor / same-draw floor: median (range) | small singles / pairs named (not graded) |",
             "|---|---|---|---|---|---|---|---|---|---|"]

    def cell(c, cls, key="ok"):
        k = c.get(cls)
        return "–" if not k else "%d/%d" % (k[key], k["n"])

    for reg, c in cells.items():
        if reg.startswith("limit"):
            continue
        fp = c.get("none")
        fps = "–" if not fp else "%d/%d" % (fp["n"] - fp["ok"], fp["n"])
        rm = max(c.get("single", {}).get("rms_max", 0), c.get("pair", {}).get("rms_max", 0))
        same = max(c.get("single", {}).get("same_max", 0), c.get("pair", {}).get("same_max", 0))
        adj = max(c.get("single", {}).get("adj_max", 0), c.get("pair", {}).get("adj_max", 0))
        fl = sorted(c.get("_floor", {}).get("ratios", []))
        fls = "–" if not fl else "%.2f (%.2f-%.2f)" % (fl[len(fl) // 2], fl[0], fl[-1])
        def ratio(x):
            return "%.2f" % x if x > 0 else "–"

        lines.append("| %s | %s | %s | %s | %s (%s) | %s | %s | %s | %s | %s / %s |" % (
            reg, fps, cell(c, "single"), cell(c, "pair"), cell(c, "blunders", "found"),
            cell(c, "blunders"), cell(c, "ripple"),
            ratio(same) if adj <= 0 else "%s (%s)" % (ratio(same), ratio(adj)), ratio(rm), fls,
            cell(c, "small single"), cell(c, "small pair")))
    lim = [(reg, c) for reg, c in cells.items() if reg.startswith("limit")]
    if lim:
        lines += ["", "| visible effect (RMS the paper's model cannot absorb, × noise) | singles named |", "|---|---|"]
        for reg, c in sorted(lim, key=lambda x: float(x[0].split()[1])):
            k = {"n": 0, "ok": 0}
            for cls in ("single", "small single"):
                k["n"] += c.get(cls, {}).get("n", 0)
                k["ok"] += c.get(cls, {}).get("ok", 0)
            lines.append("| %s | %d/%d |" % (reg.split()[1], k["ok"], k["n"]))
    return "\n".join(lines)


def limit_points(cells):
    """(visible size, named fraction, n) of the detection-limit rows."""
    pts = []
    for reg, c in cells.items():
        if not reg.startswith("limit"):
            continue
        n = sum(c.get(k, {}).get("n", 0) for k in ("single", "small single"))
        ok = sum(c.get(k, {}).get("ok", 0) for k in ("single", "small single"))
        if n:
            pts.append((float(reg.split()[1]), ok / n, n))
    return sorted(pts)


def svg(cells, path):
    """The detection-limit curve as a small SVG (no plotting package)."""
    pts = limit_points(cells)
    w, h, l, b, t, r = 520, 320, 60, 50, 20, 20
    xmax = 3.0

    def x(v):
        return l + (w - l - r) * v / xmax

    def y(v):
        return h - b - (h - b - t) * v

    out = ['<svg xmlns="http://www.w3.org/2000/svg" width="%d" height="%d" font-family="sans-serif" font-size="12">' % (w, h),
           '<rect width="100%" height="100%" fill="white"/>']
    for v in (0, 0.25, 0.5, 0.75, 1.0):
        out.append('<line x1="%d" x2="%d" y1="%.1f" y2="%.1f" stroke="#ddd"/>' % (l, w - r, y(v), y(v)))
        out.append('<text x="%d" y="%.1f" text-anchor="end">%d %%</text>' % (l - 6, y(v) + 4, 100 * v))
    for v in (0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0):
        out.append('<text x="%.1f" y="%d" text-anchor="middle">%.1f</text>' % (x(v), h - b + 16, v))
    out.append('<line x1="%d" x2="%d" y1="%.1f" y2="%.1f" stroke="#c33" stroke-dasharray="4 3"/>' % (l, w - r, y(0.9), y(0.9)))
    out.append('<text x="%d" y="%.1f" fill="#c33" text-anchor="end">90 %%</text>' % (w - r, y(0.9) - 4))
    out.append('<polyline fill="none" stroke="#236" stroke-width="2" points="%s"/>' % " ".join(
        "%.1f,%.1f" % (x(a), y(f)) for a, f, _ in pts))
    for a, f, n in pts:
        out.append('<circle cx="%.1f" cy="%.1f" r="4" fill="#236"><title>%d runs</title></circle>' % (x(a), y(f), n))
        out.append('<text x="%.1f" y="%.1f" font-size="10" text-anchor="middle">n=%d</text>' % (x(a), y(f) - 8, n))
    out.append('<text x="%d" y="%d" text-anchor="middle">visible effect: RMS the paper\'s model cannot absorb, × visible noise</text>' % ((l + w - r) // 2, h - 12))
    out.append('<text transform="translate(16,%d) rotate(-90)" text-anchor="middle">single effects named</text>' % ((t + h - b) // 2))
    out.append("</svg>")
    with open(path, "w") as f:
        f.write("\n".join(out) + "\n")


def regime_jobs(regimes, truths, n_null, n_eff, seed):
    """Per regime: `n_null` effect-free runs, then `n_eff` rounds of every
    truth; seeds counted up from `seed`. Returns the jobs and the last seed."""
    jobs = []
    for reg in regimes:
        for j in range(n_null):
            seed += 1
            jobs.append((reg[0], "none", make_case(reg, "none", seed, 0, ["ring45", "tian30"][j % 2])))
        for j in range(n_eff):
            for truth in truths:
                seed += 1
                geo = ["ring45", "tian30"][(j + seed) % 2]
                jobs.append((reg[0], truth, make_case(reg, truth, seed, 2.0, geo)))
    return jobs, seed


def plan_offcat(seed_base, n_null, n_eff):
    """The off-catalogue block (OFFCAT): per regime, effect-free runs, then
    every single (the catalogue's and OFFCAT_SINGLES) and spatter."""
    return regime_jobs(OFFCAT, SINGLES + OFFCAT_SINGLES + ["spatter"], n_null, n_eff, seed_base)[0]


def main():
    if "--v3" in sys.argv[1:]:
        # the cases of issue 35 (v3.py), not part of the grid nor of CI
        import v3
        sys.exit(v3.main([x for x in sys.argv[1:] if x != "--v3"]))
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--perpend", required=True)
    ap.add_argument("--v3", action="store_true",
                    help="the v3 block instead (v3.py: the cases of issue 35, its own options)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json")
    ap.add_argument("--md")
    ap.add_argument("--check", action="store_true")
    ap.add_argument("--svg", help="write the detection-limit curve (full grid) as SVG")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--seed-base", type=int, default=TUNE_SEEDS,
                    help="first seed of the grid (default: the tuning range; report with another)")
    ap.add_argument("--nulls", type=int,
                    help="effect-free runs per regime (default 20, 8 with --quick)")
    ap.add_argument("--effects", type=int,
                    help="runs per effect class and regime (default 5, 2 with --quick)")
    ap.add_argument("--runs", help="write one JSON line per run (case, truth, answer, grade) here")
    ap.add_argument("--only", help="comma-separated truths to run (e.g. none): a subset of the grid")
    ap.add_argument("--regime", help="comma-separated regimes to run (e.g. '120 poses'): a subset of the grid")
    ap.add_argument("--from-runs", help="summarise a --runs file instead of running the grid")
    ap.add_argument("--combined", action="store_true",
                    help="the base regime and regimes with two factors at once (COMBINED) instead of the grid")
    ap.add_argument("--offcat", action="store_true",
                    help="the off-catalogue block (OFFCAT: other noise, missing readings, spatter, "
                         "effect shapes outside both catalogues) instead of the grid")
    a = ap.parse_args()
    if a.from_runs:
        results = []
        with open(a.from_runs) as f:
            for line in f:
                x = json.loads(line)
                t = x["truth"]
                truth = tuple(t.split("+")) if "+" in t else t
                r = ({"case": x["hidden"]["case"], "out": x["answer"], "truth": x["hidden"]}
                     if x.get("answer") else {"case": {"seed": x["seed"]}, "error": str(x["grade"].get("why"))})
                results.append((x["regime"], truth, r))
        cells = summarise(results)
        print(markdown(cells))
        if a.md:
            with open(a.md, "w") as f:
                f.write(markdown(cells) + "\n")
        if a.svg:
            svg(cells, a.svg)
        return 0
    jobs = plan(a.quick, a.seed_base, a.nulls, a.effects, a.combined, a.offcat)
    if a.only:
        keep = set(a.only.split(","))
        jobs = [j for j in jobs if (j[1] if isinstance(j[1], str) else "+".join(j[1])) in keep]
    if a.regime:
        keep = set(a.regime.split(","))
        jobs = [j for j in jobs if j[0] in keep]
    with cf.ThreadPoolExecutor(a.jobs) as ex:
        outs = list(ex.map(run_one, [(a.perpend, j[2]) for j in jobs]))
    results = [(j[0], j[1], o) for j, o in zip(jobs, outs)]
    cells = summarise(results)
    if a.runs:
        with open(a.runs, "w") as f:
            for reg, truth, r in results:
                t = truth if isinstance(truth, str) else "+".join(truth)
                f.write(json.dumps({"regime": reg, "truth": t, "grade": grade(r),
                                    "seed": r["case"]["seed"], "hidden": r.get("truth"),
                                    "answer": r.get("out")}) + "\n")
    md = markdown(cells)
    # with --json -, the JSON alone goes to standard output, the rest to standard error
    out = sys.stderr if a.json == "-" else sys.stdout
    print(md, file=out)
    for reg, c in cells.items():
        for cls, k in c.items():
            for w in k.get("wrong", [])[:6]:
                print("  %s / %s: %s" % (reg, cls, w), file=sys.stderr)
    if a.json:
        grid = json_grid(cells)
        if a.json == "-":
            json.dump(grid, sys.stdout, indent=1)
            print()
        else:
            with open(a.json, "w") as f:
                json.dump(grid, f, indent=1)
    if a.md:
        with open(a.md, "w") as f:
            f.write(md + "\n")
    if a.svg:
        svg(cells, a.svg)
    n = len(results)
    errors = [r for _, _, r in results if "error" in r]
    if a.quick:
        fails, summary = pooled_check(cells)
        print("blind: %d runs (%s), %d goals missed" % (n, summary, len(fails)), file=out)
    else:
        fails = check(cells)
        print("blind: %d runs, %d per-regime goals missed" % (n, len(fails)), file=out)
    fails += ["%d runs ended in an error, e.g. %s" % (len(errors), errors[0]["error"][:300])] if errors else []
    for f in fails:
        print("  missed: " + f, file=out)
    if a.check and fails:
        sys.exit(1)


if __name__ == "__main__":
    main()

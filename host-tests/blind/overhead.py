#!/usr/bin/env python3
"""What fitting a candidate costs when there is nothing to find.

On effect-free runs of gen.py (which shares no code with perpend), every
candidate model's held-out RMS, as `perpend diagnose --json` reports it in
`candidates`, is divided by gen.py's same-draw floor (`oracle_heldout_mm`:
zero point and direction fitted, 5 parameters per sensor, held out as the
diagnosis holds out). The ratio is the variance a model's extra
coefficients add on these draws: a lower bound, for that model, of the
"extended held-out RMS / same-draw floor" the grid grades where an effect
is named, whatever the effect's shape. Printed per regime and model: the
median, the 90th percentile and the largest ratio.

    overhead.py --perpend target/debug/perpend [--runs N] [--seed-base S]
                [--regime NAMES] [--jobs J]

Standard library only.
"""

import argparse
import concurrent.futures as cf
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import score  # noqa: E402


def quantile(xs, q):
    """Linear interpolation between order statistics."""
    xs = sorted(xs)
    if not xs:
        return float("nan")
    pos = q * (len(xs) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (pos - lo)


def ratios(result):
    """{model: held-out RMS / same-draw floor} of one run (empty on error)."""
    if "error" in result:
        return {}
    same = score.same_draw_floor(result)
    if not same > 0:
        return {}
    return {c["effect"]: c["heldout_rms_mm"] / same for c in result["out"]["candidates"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--perpend", required=True)
    ap.add_argument("--runs", type=int, default=20, help="effect-free runs per regime")
    ap.add_argument("--seed-base", type=int, default=1400000)
    ap.add_argument("--regime", default="base,sigma 0.002,spread 15 deg,30 poses,120 poses")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    regimes = dict(score.REGIMES)
    names = [r.strip() for r in a.regime.split(",")]
    for name in names:
        if name not in regimes:
            sys.exit(f"unknown regime {name!r}; known: {', '.join(regimes)}")
    jobs = []
    for r, name in enumerate(names):
        for j in range(a.runs):
            seed = a.seed_base + 1000 * r + j
            geometry = ["ring45", "tian30"][j % 2]
            case = score.make_case((name, regimes[name]), "none", seed, 0, geometry)
            jobs.append((name, (a.perpend, case)))
    with cf.ThreadPoolExecutor(a.jobs) as ex:
        done = list(ex.map(lambda j: (j[0], ratios(score.run_one(j[1]))), jobs))
    print("| regime | model | runs | median | p90 | max |")
    print("|---|---|---|---|---|---|")
    for name in names:
        per = {}
        for n, rs in done:
            if n == name:
                for m, x in rs.items():
                    per.setdefault(m, []).append(x)
        for m, xs in per.items():
            print(f"| {name} | {m} | {len(xs)} | {quantile(xs, 0.5):.3f} | "
                  f"{quantile(xs, 0.9):.3f} | {max(xs):.3f} |")


if __name__ == "__main__":
    main()

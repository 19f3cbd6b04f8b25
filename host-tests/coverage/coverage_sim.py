#!/usr/bin/env python3
"""What U = k·u covers in the cell's conformity decision (docs/record.md,
"What the coverage factor covers"): a Monte Carlo of the measured normal
error e = |d|, d = d0 + a 2-D normal error of standard uncertainty u per
axis, against the true error |d0|. Standard library only; seeded.

For each true error |d0|/u it prints
- the 2-D radius coverage P(|d − d0| ≤ 2u): 86 % whatever |d0| (the figure
  a reviewer measured as 82.5 % on poses);
- the coverage that decides: P(| |d| − |d0| | ≤ 2u), the error's size;
- the one-sided false acceptance of the guarded rule at a true error just
  at the tolerance (|d0| = T): P(e + 2u ≤ T), which must stay ≤ 2.3 %.

Usage: python3 host-tests/coverage/coverage_sim.py [--draws N] [--seed S]
"""
import argparse
import math
import random


def row(r, draws, rng):
    """Coverages at true error r·u (u = 1)."""
    radius = size = 0
    for _ in range(draws):
        dx, dy = rng.gauss(0.0, 1.0), rng.gauss(0.0, 1.0)
        e = math.hypot(r + dx, dy)
        radius += math.hypot(dx, dy) <= 2.0
        size += abs(e - r) <= 2.0
    return radius / draws, size / draws


def false_accept(r, draws, rng):
    """P(e + 2u ≤ T) with the true error at the tolerance T = r·u."""
    hits = 0
    for _ in range(draws):
        e = math.hypot(r + rng.gauss(0.0, 1.0), rng.gauss(0.0, 1.0))
        hits += e + 2.0 <= r
    return hits / draws


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200000)
    ap.add_argument("--seed", type=int, default=45)
    a = ap.parse_args()
    rng = random.Random(a.seed)
    print("| true error / u | 2-D radius within 2u | size within 2u | "
          "false acceptance at T = true error |")
    print("|---|---|---|---|")
    for r in [0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0]:
        radius, size = row(r, a.draws, rng)
        fa = false_accept(r, a.draws, rng) if r > 0 else float("nan")
        fa_s = "-" if r == 0 else f"{100 * fa:.2f} %"
        print(f"| {r:g} | {100 * radius:.1f} % | {100 * size:.1f} % | {fa_s} |")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Would a higher-order linearity polynomial follow an S-shaped (one sine
period over the run's span) linearity error better than perpend's cubic?

For runs of gen.py with `linearity_s`, every sensor is fitted, by the same
10-fold cross-validation by pose as the diagnosis, with zero point +
direction (5 parameters) plus: nothing (the paper's model), a cubic
(perpend's `nonlinearity`), a quintic, or a natural cubic spline with 5
knots at quantiles of the run's readings (4 coefficients; linear beyond
the outer knots), all in the predicted distance about the mean reading.
Printed: each model's held-out RMS over gen.py's same-draw floor
(`oracle_heldout_mm`). Standard library only; shares no code with perpend.

    probe_linearity.py [--runs N]

Answer (`--runs 4`, seeds 9000-9003, docs/diagnosis.md): at 60 poses the
quintic beats the cubic in 3 of 8 runs and the spline in 8 of 8 (to
1.05-1.37x the floor, against the cubic's 1.08-1.41x); at 30 poses the
spline wins 1 of 4 and the quintic none (up to 10x). perpend now has
such a table (`linearity_table`: natural spline, knots at the 1-99 %
quantiles, values at the interior knots fitted, stored in record v2);
docs/diagnosis.md gives what it did on the blind grid.
"""

import argparse
import math
import os
import random
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gen  # noqa: E402
import score  # noqa: E402
from gen import add, beam_distance, cross, gauss_newton, scale, unit  # noqa: E402


def power_basis(deg):
    """x, x², …, x^deg."""
    return lambda x: [x ** (j + 1) for j in range(deg)]


def spline_basis(knots):
    """Natural cubic spline in x with the given knots, less the constant
    (Hastie, Tibshirani & Friedman, ESL eq. 5.4-5.5): linear beyond the
    outer knots."""
    kk = len(knots)

    def d(x, k):
        a = max(0.0, x - knots[k]) ** 3 - max(0.0, x - knots[-1]) ** 3
        return a / (knots[-1] - knots[k])

    return lambda x: [x] + [d(x, k) - d(x, kk - 2) for k in range(kk - 2)]


def fit_poly(e, u, planes, target, basis, nb, dref):
    """Zero point, direction and `nb` coefficients of `basis` in the
    predicted distance about `dref`, by damped Gauss-Newton (numerical
    derivatives); returns the predictor."""
    t1 = unit(cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0]))
    t2 = cross(u, t1)
    npar = 5 + nb

    def model(p, pls):
        e2 = add(e, p[:3])
        u2 = unit(add(add(u, scale(t1, p[3])), scale(t2, p[4])))
        out = []
        for pl in pls:
            f = beam_distance(e2, u2, pl)
            b = basis(f - dref) if nb else []
            out.append(f + sum(p[5 + j] * b[j] for j in range(nb)))
        return out

    p = gauss_newton(lambda q: model(q, planes), npar, target, 8,
                     lambda j: 1e-8 if j in (3, 4) else 1e-6, True)
    return lambda pls: model(p, pls)


MODELS = ["paper", "cubic", "quintic", "spline5"]


def probe(case, k=10):
    nominal, rows, truth = gen.generate(case)
    planes = [r["plane"] for r in rows]
    reads = [r["reads"] for r in rows]
    n = len(rows)
    order = list(range(n))
    random.Random(1).shuffle(order)
    fold = {j: i % k for i, j in enumerate(order)}
    res = {m: [] for m in MODELS}
    for i in range(4):
        xs = sorted(r[i] for r in reads)
        dref = sum(xs) / n
        # spline knots at quantiles of the run's readings (5 %, …, 95 %)
        knots = [xs[int(a * (n - 1))] - dref for a in (0.05, 0.275, 0.5, 0.725, 0.95)]
        bases = {"paper": (None, 0), "cubic": (power_basis(3), 3),
                 "quintic": (power_basis(5), 5), "spline5": (spline_basis(knots), 4)}
        for f in range(k):
            tr = [j for j in range(n) if fold[j] != f]
            te = [j for j in range(n) if fold[j] == f]
            for m in MODELS:
                basis, nb = bases[m]
                pred = fit_poly(nominal[i][0], nominal[i][1], [planes[j] for j in tr],
                                [reads[j][i] for j in tr], basis, nb, dref)
                res[m] += [reads[j][i] - p for j, p in zip(te, pred([planes[j] for j in te]))]
    orc = [x for r in truth["oracle_heldout_mm"] for x in r if x is not None]
    floor = math.sqrt(sum(x * x for x in orc) / len(orc))
    return {m: math.sqrt(sum(x * x for x in v) / len(v)) / floor for m, v in res.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=4)
    a = ap.parse_args()
    print("regime        seed   held-out RMS / same-draw floor: " + ", ".join(MODELS))
    for reg in [r for r in score.REGIMES if r[0] in ("base", "30 poses", "sigma 0.002")]:
        for seed in range(9000, 9000 + a.runs):
            case = score.make_case(reg, "linearity_s", seed, 2.0, ["ring45", "tian30"][seed % 2])
            r = probe(case)
            print("%-12s %5d   %s" % (reg[0], seed, "  ".join("%.3f" % r[m] for m in MODELS)))


if __name__ == "__main__":
    main()

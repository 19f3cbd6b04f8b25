#!/usr/bin/env python3
"""Checks of the oracle (oracle.py) and of the bench that sets the
diagnosis beside it (power.py), standard library only:
`python3 host-tests/blind/test_oracle.py`; run.sh runs it first in every
mode (CI included), about 10 s."""

import math
import os
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cases  # noqa: E402
import gen  # noqa: E402
import oracle  # noqa: E402
import power  # noqa: E402


def case(kinds, seed, size, poses=30, geometry="ring45", **extra):
    """A run of `poses` poses at the base noise with `kinds` ([kind, n
    sensors or 0]) at `size` x the visible noise."""
    c = dict(cases.BASE)
    c.update({"seed": seed, "geometry": geometry, "blunders": 0, "poses": poses})
    c.update(extra)
    s = cases.noise_scale(c) * size
    c["effects"] = [[k, s, n] if n else [k, s] for k, n in kinds]
    return c


def p_values(c):
    _, rows, _, state = gen.generate_full(c)
    return [t["p"] for t in oracle.judge_run(state, rows)]


class FDistribution(unittest.TestCase):
    def test_against_closed_forms(self):
        # I_x(1, 1) = x; F(2, d2): P(F > f) = (1 + 2 f / d2)^(-d2 / 2)
        for x in (0.01, 0.3, 0.77):
            self.assertAlmostEqual(oracle.betainc(1.0, 1.0, x), x, places=12)
        for d2 in (5, 30, 200):
            for f in (0.1, 1.0, 4.0, 12.0):
                self.assertAlmostEqual(oracle.f_sf(f, 2, d2), (1 + 2 * f / d2) ** (-d2 / 2), places=10)
        # F(1, d2) is t^2: P(F > 4.0) at d2 = 1 is P(|t_1| > 2) = 1 - 2 atan(2) / pi
        self.assertAlmostEqual(oracle.f_sf(4.0, 1, 1), 1 - 2 * math.atan(2.0) / math.pi, places=10)


class Oracle(unittest.TestCase):
    def test_unit_form_knows_the_shape_not_the_sensors(self):
        c = case([["thermal_lag", 1]], 7, 2.0)
        _, _, _, state = gen.generate_full(c)
        kind, par = state["effects"][0]
        self.assertEqual(sum(par["mask"]), 1)
        x = oracle.form_columns(state, kind, par)
        # the form is there on all four sensors, though the effect is on one
        for i in range(4):
            self.assertGreater(max(abs(r[i]) for r in x), 0.0)
        self.assertNotIn("mask", oracle.unit_par(kind, par))

    def test_effect_on_one_sensor_only_moves_that_sensor(self):
        quiet = {"sigma_mm": 1e-12, "tracker_factor": 0.0}
        _, rows, _, state = gen.generate_full(case([["gain", 1]], 9, 2.0, **quiet))
        _, rows0, _ = gen.generate(case([], 9, 0.0, **quiet))
        on = state["effects"][0][1]["mask"]
        for r, r0 in zip(rows, rows0):
            for i in range(4):
                if not on[i]:
                    self.assertAlmostEqual(r["reads"][i], r0["reads"][i], delta=1e-9)

    def test_on_effect_free_draws_it_rejects_about_its_level(self):
        # 48 null tests (forms drawn, amplitudes zero): at 0.05 expect 2.4
        ps = []
        kinds = ["gain", "crosstalk", "thermal_lag", "drift_settle", "linearity_s", "tracker_drift"]
        for s in range(8):
            for j, k in enumerate(kinds):
                ps += p_values(case([[k, 0]], 100 + 10 * s + j, 0.0, geometry=["ring45", "skew"][s % 2]))
        self.assertLessEqual(sum(p < 0.05 for p in ps), 7, ps)
        self.assertLessEqual(sum(p < oracle.candidate_level() for p in ps), 1, ps)
        # and they are spread, not all near 1 (a test that never rejects)
        self.assertTrue(0.3 < sum(ps) / len(ps) < 0.7, sum(ps) / len(ps))
        self.assertGreater(sum(p < 0.3 for p in ps), 6)

    def test_a_large_effect_is_rejected(self):
        # asked 2x the visible noise; at least 0.9x reached (gen.PHYSICAL caps
        # an effect on one sensor)
        for kinds in ([["thermal_lag", 0]], [["thermal_lag", 1]], [["tracker_drift", 0]]):
            for s in range(2):
                c = case(kinds, 300 + s, 2.0)
                _, rows, hidden, state = gen.generate_full(c)
                self.assertGreater(hidden["visible_rms_mm"][0], 0.9 * cases.noise_scale(c))
                p = oracle.judge_run(state, rows)[0]["p"]
                self.assertLess(p, oracle.candidate_level(), (kinds, p))

    def test_each_effect_of_three_is_tested_beside_the_others(self):
        c = case([["gain", 0], ["thermal_lag", 0], ["crosstalk", 0]], 41, 0.0)
        c["effects"][1][1] = cases.noise_scale(c) * 2.0  # only the thermal is there
        p = p_values(c)
        self.assertLess(p[1], oracle.candidate_level())
        self.assertGreater(min(p[0], p[2]), oracle.candidate_level(), p)


class Bench(unittest.TestCase):
    def row(self, kinds, p, named, effect=None, size=1.0, regime="base", cls="x"):
        return {"class": cls, "regime": regime, "size": size, "seed": 1, "kinds": kinds, "p": p,
                "visible": [size] * len(kinds), "normal_cost": 1.5, "m": 7,
                "named": named, "effect": effect or (named[0] if named else "none")}

    def test_named_right_wrong_and_the_ratio(self):
        rows = [self.row(["gain"], [1e-9], ["nonlinearity"]),        # both
                self.row(["gain"], [1e-9], []),                       # oracle only
                self.row(["gain"], [0.2], ["gain", "thermal"]),       # diagnosis only, one wrong
                self.row(["drift_settle"], [1e-9], ["drift"]),
                self.row([], [], [], size=0.0),
                self.row(["gain"], [0.5], ["gain"], size=0.0)]        # a false positive
        cells, nulls = power.summarise(rows)
        c = cells[("x", "", 1.0)]
        self.assertEqual((c["n"], c["oracle"], c["diag"], c["wrong"]), (4, 3, 3, 1))
        self.assertEqual((nulls["base"]["diag"], nulls["base"]["fp"]), (2, 1))
        p = power.pooled(cells, nulls)
        self.assertAlmostEqual(p["ratio"], 1.0)
        fails = power.ci_gates(p)
        self.assertTrue(any("false positives 1/2" in f for f in fails), fails)

    def test_goal_counts_cells_where_the_oracle_sees_it(self):
        rows = [self.row(["gain"], [1e-9], [], cls="a") for _ in range(3)]
        rows += [self.row(["gain"], [0.9], [], cls="b") for _ in range(3)]
        cells, nulls = power.summarise(rows)
        misses, fps = power.goal_misses(cells, nulls)
        self.assertEqual(len(misses), 1)
        self.assertTrue(misses[0].startswith("a at 1.00"), misses)
        self.assertTrue(any("ratio" in f for f in power.ci_gates(power.pooled(cells, nulls))))


if __name__ == "__main__":
    unittest.main()

#!/usr/bin/env python3
"""Checks of gen.py's v3 additions (issue 35, item 5), standard library
only: `python3 host-tests/blind/test_v3.py`; run.sh runs it first in
every mode (CI included)."""

import math
import os
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gen  # noqa: E402
import score  # noqa: E402
import v3  # noqa: E402


def quiet(case):
    """The case without reading or tracker noise."""
    case = dict(case)
    case.update({"sigma_mm": 1e-12, "tracker_factor": 0.0})
    return case


class V3(unittest.TestCase):
    def test_normal_cost_leaves_the_draw_of_a_run_unchanged(self):
        # the grid's cases do not set normal_cost: with it, the same
        # readings and planes must come out (it draws from its own stream)
        case = score.make_case(score.REGIMES[0], "gain", 4242, 2.0, "ring45")
        _, rows, truth = gen.generate(case)
        _, rows2, truth2 = gen.generate(dict(case, normal_cost=True))
        self.assertEqual(rows, rows2)
        self.assertEqual(truth["oracle_heldout_mm"], truth2["oracle_heldout_mm"])
        self.assertNotIn("normal_cost", truth)
        self.assertIn("normal_cost", truth2)

    def test_effect_free_run_costs_nothing_and_a_large_effect_costs(self):
        none = v3.make_v3_case("base", [], 11, 0.0, "ring45")
        self.assertAlmostEqual(gen.generate(none)[2]["normal_cost"], 1.0, delta=1e-9)
        big = v3.make_v3_case("base", ["hysteresis"], 11, 3.0, "ring45")
        self.assertGreater(gen.generate(big)[2]["normal_cost"], 1.3)

    def test_hysteresis_follows_the_sign_of_each_sensors_last_move(self):
        case = quiet(v3.make_v3_case("base", ["hysteresis"], 5, 2.0, "ring45"))
        _, rows, truth = gen.generate(case)
        clean = quiet(v3.make_v3_case("base", [], 5, 0.0, "ring45"))
        _, rows0, _ = gen.generate(clean)
        h = truth["effect_par"][0][1]["h"]
        for k in range(1, len(rows)):
            for i in range(4):
                moved_out = rows0[k]["reads"][i] >= rows0[k - 1]["reads"][i]
                err = rows[k]["reads"][i] - rows0[k]["reads"][i]
                self.assertAlmostEqual(err, -h[i] if moved_out else h[i], delta=1e-6)

    def test_warm_up_plateau_parts_from_the_time_and_the_ramp_does_not(self):
        for name, lo, hi in (("warm-up plateau", 0.3, 0.8), ("warm-up no plateau", 0.98, 1.0)):
            case = v3.make_v3_case(name, ["drift_linear", "thermal_tied"], 21, 1.0, "tian30")
            r = gen.generate(case)[2]["temp_time_r"]
            self.assertTrue(lo <= r <= hi, (name, r))

    def test_only_takes_case_names_that_hold_commas_whole(self):
        self.assertEqual(v3.only_cases("gain, two sensors,incidence spot, 5 deg"),
                         {"gain, two sensors", "incidence spot, 5 deg"})
        self.assertEqual(v3.only_cases("none,incidence spot"), {"none", "incidence spot"})
        with self.assertRaises(SystemExit):
            v3.only_cases("gain")

    def test_quick_gates_pool_the_null_runs_and_the_graded_cases(self):
        def rows(case, regime, n, ok, graded=True):
            return [{"case": case, "regime": regime, "size": 1.0, "cost": 1.5, "graded": graded,
                     "ok": k < ok, "said": "x"} for k in range(n)]
        # one false positive in 36 null runs (2.8 %) passes pooled; the
        # per-regime rule would fail its regime (1/6)
        good = rows("none", "base", 6, 5) + rows("none", "spread 15 deg", 30, 30)
        good += rows("hysteresis", "base", 10, 9) + rows("incidence spot", "base", 10, 10)
        self.assertEqual(v3.pooled_check(v3.summarise(good)), [])
        self.assertTrue(v3.check(v3.summarise(good)))
        # two in 36 (5.6 %) fail, as does a case named in fewer than half
        bad = rows("none", "base", 6, 4) + rows("none", "spread 15 deg", 30, 30)
        bad += rows("hysteresis", "base", 30, 30) + rows("incidence spot", "base", 4, 1)
        fails = v3.pooled_check(v3.summarise(bad))
        self.assertEqual(len(fails), 2, fails)
        self.assertTrue(fails[0].startswith("false positives 2/36"), fails)
        self.assertTrue(fails[1].startswith("incidence spot: named in 1 of 4"), fails)

    def test_tracker_tilt_turns_against_the_head(self):
        eps = [0.05, -0.03]
        case = quiet({"seed": 3, "geometry": "ring45", "declared": 1.0, "spread_deg": 8.0,
                      "poses": 16, "effects": [], "blunders": 0, "reversal": 4,
                      "tracker_tilt_deg": eps})
        _, rows, truth = gen.generate(case)
        size = math.radians(math.hypot(*eps))
        seen = []
        for k, r in enumerate(rows):
            w = gen.cross(truth["true_planes"][k][0], r["plane"][0])
            self.assertAlmostEqual(gen.norm(w), size, delta=1e-3 * size)
            seen.append(math.atan2(w[1], w[0]))
        # four joint angles of one planned pose: the error turns by -90 deg each
        for k in range(3):
            turn = (seen[k + 1] - seen[k] + math.pi) % (2 * math.pi) - math.pi
            self.assertAlmostEqual(turn, -math.pi / 2, delta=0.02)


if __name__ == "__main__":
    unittest.main()

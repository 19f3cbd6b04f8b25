"""Checks of score.py's grading arithmetic (standard library only):
the least cost of estimating the named model's coefficients, which the
goal on the extended held-out RMS divides by."""

import math
import os
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import score  # noqa: E402


def answer(params, folds=10, outliers=()):
    return {"candidates": [{"effect": e, "n_params": p} for e, p in params.items()],
            "folds": folds, "outlier_poses": [{"pose": k} for k in outliers]}


def run(out, poses=30):
    return {"out": out, "truth": {"oracle_heldout_mm": [[0.01] * 4 for _ in range(poses)]}}


class EstimationCost(unittest.TestCase):
    def test_a_pair_adds_both_extras(self):
        r = run(answer({"none": 20, "thermal": 24, "gain": 24}))
        # 120 readings, 108 trained per fold: sqrt((1 + 28/108) / (1 + 20/108))
        want = math.sqrt((1 + 28 / 108) / (1 + 20 / 108))
        self.assertAlmostEqual(score.estimation_cost(r, ["thermal", "gain"]), want, places=12)
        self.assertAlmostEqual(want, 1.0308, places=4)

    def test_more_readings_cost_less(self):
        short = score.estimation_cost(run(answer({"none": 20, "linearity_table": 36})), ["linearity_table"])
        long_ = score.estimation_cost(run(answer({"none": 20, "linearity_table": 36}), 120),
                                      ["linearity_table"])
        self.assertGreater(short, long_)
        self.assertGreater(long_, 1.0)

    def test_outlier_poses_are_not_readings(self):
        r = run(answer({"none": 20, "gain": 24}, outliers=(1, 2)))
        n = 28 * 4 * 9 / 10
        want = math.sqrt((1 + 24 / n) / (1 + 20 / n))
        self.assertAlmostEqual(score.estimation_cost(r, ["gain"]), want, places=12)

    def test_without_the_counts_nothing_is_allowed(self):
        self.assertEqual(score.estimation_cost(run(answer({"none": 20})), ["gain"]), 1.0)
        self.assertEqual(score.estimation_cost(run(answer({"none": 20, "gain": 24}, folds=None)), ["gain"]), 1.0)
        self.assertEqual(score.estimation_cost(run(answer({"gain": 24})), ["gain"]), 1.0)


if __name__ == "__main__":
    unittest.main()

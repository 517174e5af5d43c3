"""What two systems' errors share on one sequence (plvo_eval.shared_error): a common error recovered, none invented."""

from __future__ import annotations

import numpy as np
import pytest

from plvo_eval.shared_error import segment_translation_errors, shared_error


def _path(heights: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Camera poses (y down, z ahead) along a straight road at the given heights (m, up) and step lengths."""
    poses = np.tile(np.eye(4), (len(heights), 1, 1))
    poses[:, 2, 3] = np.concatenate([[0.0], np.cumsum(steps[1:])])
    poses[:, 1, 3] = -heights
    return poses


def _smooth_wander(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """A slow wander (a random walk smoothed over ~10 frames), as a GPS/INS's height drifts."""
    walk = np.cumsum(rng.standard_normal(n)) * sigma
    return np.convolve(walk, np.ones(10) / 10, mode="same")


@pytest.mark.parametrize("seed", [0, 1])
def test_a_wander_of_the_truth_shows_as_what_both_share(seed):
    rng = np.random.default_rng(seed)
    n = 400
    steps = np.full(n, 1.4)
    true = _path(np.zeros(n), steps)  # what the car did: a flat road
    truth = _path(_smooth_wander(rng, n, 0.006), steps)  # what the truth says: a wandering height
    est_a = _path(rng.standard_normal(n) * 0.004, steps * (1 + rng.standard_normal(n) * 0.003))
    est_b = _path(rng.standard_normal(n) * 0.004, steps * (1 + rng.standard_normal(n) * 0.003))
    out = shared_error(truth, est_a, est_b, (10.0, 20.0))
    for length in ("10", "20"):
        expected = np.sqrt(np.mean(segment_translation_errors(truth, true, float(length))[1] ** 2, axis=0))
        v = out[length]
        # the truth's height wander is what both share: recovered within 15 %, and nothing shared along z or x
        assert v["shared_rms"][1] == pytest.approx(expected[1], rel=0.1)  # measured within 2 % over six seeds
        assert v["correlation"][1] > 0.5 and v["shared_rms"][2] < 0.5 * v["own_a"][2]
        assert v["own_a_norm"] < v["total_a_norm"] and v["own_b_norm"] < v["total_b_norm"]


def test_independent_errors_share_nothing():
    rng = np.random.default_rng(3)
    n = 400
    steps = np.full(n, 1.4)
    truth = _path(np.zeros(n), steps)
    est_a = _path(_smooth_wander(rng, n, 0.004), steps)
    est_b = _path(_smooth_wander(rng, n, 0.004), steps)
    v = shared_error(truth, est_a, est_b, (20.0,))["20"]
    assert abs(v["correlation"][1]) < 0.35
    assert v["own_a_norm"] > 0.8 * v["total_a_norm"] and v["own_b_norm"] > 0.8 * v["total_b_norm"]
    assert shared_error(truth[:5], est_a[:5], est_b[:5], (20.0,)) == {}  # no segment of 20 m: no figure

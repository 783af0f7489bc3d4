"""``Estimate``: the record of one relocalization, printed in one short line."""

from __future__ import annotations


def test_estimate_prints_in_one_short_line():
    import numpy as np

    from mapfree.estimate import Estimate
    from mapfree.geometry import Pose

    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    est = Estimate(Pose(R, np.array([0.1, -0.2, 1.5])), 12.5, 140, extras={"matches": np.zeros((4000, 4))})
    text = str(est)
    assert "\n" not in text and len(text) < 120, text
    assert "90.00 deg" in text and "1.500" in text and "inliers 140" in text
    failed = Estimate.failure("no depth for the query image")
    assert str(failed) == "Estimate(no estimate: no depth for the query image)"

"""This session's view centres: read in bulk, the newest ``capacity`` kept."""

from __future__ import annotations

import numpy as np

from solid_ros.core.candidates.views import KeyframeViews


def test_centres_are_read_by_index_and_missing_ones_are_nan() -> None:
    views = KeyframeViews(1000)
    for i in (0, 1, 2, 5, 300):  # 300 grows the arrays past their first rows
        views.put(i, [i, 2.0 * i, -1.0])
    got = views.at([5, 3, 0, 300, 301, -1])
    np.testing.assert_array_equal(got[[0, 2, 3]], [[5, 10, -1], [0, 0, -1], [300, 600, -1]])
    assert np.isnan(got[[1, 4, 5]]).all()
    assert views.at([]).shape == (0, 3)
    views.clear()
    assert np.isnan(views.at([5])).all()


def test_a_keyframe_beyond_the_capacity_overwrites_the_oldest() -> None:
    views = KeyframeViews(4)
    for i in range(6):
        views.put(i, [float(i)] * 3)
    got = views.at(range(6))
    assert np.isnan(got[:2]).all()  # 4 and 5 took their rows
    np.testing.assert_array_equal(got[2:, 0], [2.0, 3.0, 4.0, 5.0])


def test_of_keeps_what_a_mapping_holds() -> None:
    views = KeyframeViews.of({7: [1.0, 2.0, 3.0], 2: np.array([4.0, 5.0, 6.0])})
    np.testing.assert_array_equal(views.at([2, 7]), [[4.0, 5.0, 6.0], [1.0, 2.0, 3.0]])

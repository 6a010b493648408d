"""Boxes from an instance-id image, against a hand-drawn image."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from openfly_agent.sim.instance_boxes import instance_boxes


def test_boxes_counts_and_threshold():
    ids = np.zeros((10, 20), dtype=np.int32)
    ids[2:5, 3:9] = 2  # rows 2..4, cols 3..8
    ids[7, 19] = 3  # one pixel in the corner
    ids[0, 0] = 2  # a stray pixel stretches box 2
    visible, boxes, counts = instance_boxes(ids, num_ids=4, min_pixels=1)
    assert visible.tolist() == [2, 3] and counts.tolist() == [19, 1]
    np.testing.assert_allclose(boxes[0], [(0 + 8 + 1) / 2 / 20, (0 + 4 + 1) / 2 / 10, 9 / 20, 5 / 10])
    np.testing.assert_allclose(boxes[1], [19.5 / 20, 7.5 / 10, 1 / 20, 1 / 10])
    visible, _, _ = instance_boxes(ids, num_ids=4, min_pixels=2)
    assert visible.tolist() == [2]


def test_empty_and_out_of_range():
    visible, boxes, _ = instance_boxes(np.zeros((4, 4), np.int32), 3)
    assert len(visible) == 0 and boxes.shape == (0, 4)
    with pytest.raises(ValueError, match="instance ids must lie in"):
        instance_boxes(np.full((2, 2), 9, np.int32), 3)


@settings(max_examples=40, deadline=None)
@given(ids=arrays(np.int32, st.tuples(st.integers(1, 12), st.integers(1, 12)), elements=st.integers(0, 5)))
def test_matches_a_per_id_loop(ids):
    visible, boxes, counts = instance_boxes(ids, num_ids=5, min_pixels=2)
    expected = []
    for k in range(1, 6):
        rows, cols = np.nonzero(ids == k)
        if len(rows) >= 2:
            h, w = ids.shape
            i0, i1, j0, j1 = cols.min(), cols.max(), rows.min(), rows.max()
            expected.append(
                (
                    k,
                    [(i0 + i1 + 1) / 2 / w, (j0 + j1 + 1) / 2 / h, (i1 + 1 - i0) / w, (j1 + 1 - j0) / h],
                    len(rows),
                )
            )
    assert visible.tolist() == [e[0] for e in expected]
    assert counts.tolist() == [e[2] for e in expected]
    np.testing.assert_allclose(boxes.reshape(-1, 4), np.array([e[1] for e in expected]).reshape(-1, 4))

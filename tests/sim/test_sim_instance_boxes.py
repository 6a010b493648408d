"""Boxes from an instance-id image, against a hand-drawn image."""

import numpy as np
import pytest

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

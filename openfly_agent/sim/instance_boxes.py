"""2-D boxes of every instance in an instance-id image (occlusion-aware: only visible pixels count).

Box of an id = the pixel extent of its visible pixels: columns [i0, i1], rows [j0, j1] inclusive give
(cx, cy, w, h) = ((i0 + i1 + 1) / 2 / W, (j0 + j1 + 1) / 2 / H, (i1 + 1 - i0) / W, (j1 + 1 - j0) / H).
"""

from __future__ import annotations

import numpy as np


def _row_runs(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs of equal ids along each row: start (flat index), length and id, each (R,)."""
    width = ids.shape[1]
    flat = ids.reshape(-1)
    boundary = np.empty(flat.size, dtype=bool)
    boundary[0] = True
    np.not_equal(flat[1:], flat[:-1], out=boundary[1:])
    boundary[::width] = True  # every row starts a run
    starts = np.flatnonzero(boundary)
    return starts, np.diff(starts, append=flat.size), flat[starts].astype(np.int64)


class InstanceIdError(ValueError):
    """The instance image holds ids outside [0, num_ids] (a bad read-back, never a valid render)."""


def instance_boxes(
    ids: np.ndarray, num_ids: int, min_pixels: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes of the ids 1..num_ids with at least `min_pixels` pixels in `ids` (H, W) int; 0 = background.

    Returns: visible ids (K,) int64 ascending, boxes (K, 4) float64 (cx, cy, w, h) in [0, 1] and
    pixel counts (K,). Works on the row runs of the image (a few thousand for a rendered frame), with
    histograms over the K visible ids only: no Python loop over ids or pixels.
    """
    height, width = ids.shape
    if ids.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    starts, lengths, run_id = _row_runs(ids)
    if run_id.min() < 0 or run_id.max() > num_ids:
        raise InstanceIdError(
            f"instance ids must lie in [0, {num_ids}], got [{run_id.min()}, {run_id.max()}]"
        )
    counts = np.bincount(run_id, weights=lengths, minlength=num_ids + 1).astype(np.int64)  # (N + 1,)
    visible = np.flatnonzero(counts[1:] >= max(1, min_pixels)) + 1  # (K,)
    k = len(visible)
    if k == 0:
        return visible, np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    slot_of = np.full(num_ids + 1, -1, dtype=np.int64)
    slot_of[visible] = np.arange(k)
    slot = slot_of[run_id]  # (R,) index into `visible`, -1 for background / too small
    keep = slot >= 0
    starts, lengths, slot = starts[keep], lengths[keep], slot[keep]
    row, first = np.divmod(starts, width)
    last = first + lengths - 1
    in_row = np.bincount(slot * height + row, minlength=k * height).reshape(k, height) > 0
    first_col = np.bincount(slot * width + first, minlength=k * width).reshape(k, width) > 0
    last_col = np.bincount(slot * width + last, minlength=k * width).reshape(k, width) > 0
    i0 = first_col.argmax(axis=1)
    i1 = width - 1 - last_col[:, ::-1].argmax(axis=1)
    j0 = in_row.argmax(axis=1)
    j1 = height - 1 - in_row[:, ::-1].argmax(axis=1)
    boxes = np.stack(
        [
            (i0 + i1 + 1) / (2.0 * width),
            (j0 + j1 + 1) / (2.0 * height),
            (i1 + 1 - i0) / width,
            (j1 + 1 - j0) / height,
        ],
        axis=1,
    )
    return visible, boxes, counts[visible]

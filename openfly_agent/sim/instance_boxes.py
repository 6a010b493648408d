"""2-D boxes of every instance in an instance-id image (occlusion-aware: only visible pixels count).

Box of an id = the pixel extent of its visible pixels: columns [i0, i1], rows [j0, j1] inclusive give
(cx, cy, w, h) = ((i0 + i1 + 1) / 2 / W, (j0 + j1 + 1) / 2 / H, (i1 + 1 - i0) / W, (j1 + 1 - j0) / H).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=8)
def _pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Column of every pixel in row-major order and row of every pixel in column-major order (read-only).

    Both vary fastest along their traversal, so consecutive pixels of one instance fall in different
    histogram bins (a run of equal bins would serialise bincount's increments).
    """
    cols = np.tile(np.arange(width, dtype=np.int64), height)  # (H * W,)
    rows = np.tile(np.arange(height, dtype=np.int64), width)  # (W * H,)
    cols.setflags(write=False)
    rows.setflags(write=False)
    return cols, rows


def instance_boxes(
    ids: np.ndarray, num_ids: int, min_pixels: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes of the ids 1..num_ids with at least `min_pixels` pixels in `ids` (H, W) int; 0 = background.

    Returns: visible ids (K,) int64 ascending, boxes (K, 4) float64 (cx, cy, w, h) in [0, 1] and
    pixel counts (K,). Cost: one (id, column) and one (id, row) histogram, no Python loop over ids.
    """
    height, width = ids.shape
    by_rows = ids.reshape(-1).astype(np.int64)  # (H * W,) row-major
    if by_rows.size and (by_rows.min() < 0 or by_rows.max() > num_ids):
        raise ValueError(f"instance ids must lie in [0, {num_ids}], got [{by_rows.min()}, {by_rows.max()}]")
    by_cols = ids.T.reshape(-1).astype(np.int64)  # (W * H,) column-major
    cols, rows = _pixel_grid(height, width)
    per_col = np.bincount(by_rows * width + cols, minlength=(num_ids + 1) * width).reshape(
        -1, width
    )  # (N+1, W)
    counts = per_col.sum(axis=1)  # (N + 1,)
    visible = np.flatnonzero(counts >= max(1, min_pixels))
    visible = visible[visible > 0]
    if len(visible) == 0:
        return visible, np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    per_row = np.bincount(by_cols * height + rows, minlength=(num_ids + 1) * height).reshape(-1, height)
    in_col, in_row = per_col[visible] > 0, per_row[visible] > 0  # (K, W), (K, H)
    i0 = in_col.argmax(axis=1)
    i1 = width - 1 - in_col[:, ::-1].argmax(axis=1)
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

"""2-D boxes of every instance in an instance-id image (occlusion-aware: only visible pixels count).

Box of an id = the pixel extent of its visible pixels: columns [i0, i1], rows [j0, j1] inclusive give
(cx, cy, w, h) = ((i0 + i1 + 1) / 2 / W, (j0 + j1 + 1) / 2 / H, (i1 + 1 - i0) / W, (j1 + 1 - j0) / H).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


@lru_cache(maxsize=8)
def _pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Column and row index of every pixel in row-major order: (H * W,), (H * W,) int64, read-only."""
    cols = np.tile(np.arange(width, dtype=np.int64), height)
    rows = np.repeat(np.arange(height, dtype=np.int64), width)
    cols.setflags(write=False)
    rows.setflags(write=False)
    return cols, rows


def instance_boxes(
    ids: np.ndarray, num_ids: int, min_pixels: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes of the ids 1..num_ids with at least `min_pixels` pixels in `ids` (H, W) int; 0 = background.

    Returns: visible ids (K,) int64 ascending, boxes (K, 4) float64 (cx, cy, w, h) in [0, 1] and
    pixel counts (K,).
    Cost: two bincounts over (num_ids + 1) * W and (num_ids + 1) * H bins, no Python loop over ids.
    """
    height, width = ids.shape
    flat = ids.reshape(-1).astype(np.int64)
    if flat.size and (flat.min() < 0 or flat.max() > num_ids):
        raise ValueError(f"instance ids must lie in [0, {num_ids}], got [{flat.min()}, {flat.max()}]")
    counts = np.bincount(flat, minlength=num_ids + 1)
    visible = np.flatnonzero(counts >= max(1, min_pixels))
    visible = visible[visible > 0]
    if len(visible) == 0:
        return visible, np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    cols, rows = _pixel_grid(height, width)  # (H * W,) each
    in_col = np.bincount(flat * width + cols, minlength=(num_ids + 1) * width).reshape(-1, width)[visible] > 0
    in_row = (
        np.bincount(flat * height + rows, minlength=(num_ids + 1) * height).reshape(-1, height)[visible] > 0
    )
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

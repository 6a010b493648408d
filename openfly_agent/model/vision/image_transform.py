"""The image preprocessing of a vision config: RGB frame (H, W, 3) uint8 -> model pixels (3, s, s) uint8.

A property of the vision section (`image_size`, `resize`), so a new backbone preset brings its preprocessing
with its config. Normalisation is not done here: each backbone normalises the uint8 pixels it receives.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from openfly_agent.model.config import RESIZE_MODES


@dataclass(frozen=True)
class ImageTransform:
    """Square resize to `size` with PIL bicubic (as OpenVLA's "resize-naive") or OpenCV area interpolation.

    Args:
        size: side of the square model input in pixels.
        resize: `bicubic` | `area`.
    """

    size: int
    resize: str = "bicubic"

    def __post_init__(self) -> None:
        if self.resize not in RESIZE_MODES:
            raise ValueError(f"resize={self.resize!r} is not supported; use one of {list(RESIZE_MODES)}")

    def __call__(self, rgb: np.ndarray) -> torch.Tensor:
        """(H, W, 3) uint8 RGB -> (3, size, size) uint8 tensor (a copy; frames at the size pass unchanged)."""
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"image transform expects (H, W, 3) uint8 RGB, got {rgb.dtype} {rgb.shape}")
        if rgb.shape[:2] != (self.size, self.size):
            if self.resize == "bicubic":
                from PIL import Image

                rgb = np.asarray(Image.fromarray(rgb).resize((self.size, self.size), Image.BICUBIC))
            else:
                import cv2

                rgb = cv2.resize(rgb, (self.size, self.size), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(np.array(rgb, dtype=np.uint8, copy=True)).permute(2, 0, 1).contiguous()

"""Top-down trajectory plots (ground truth vs agent) and egocentric GIFs with the predicted box.

Matplotlib is used through its object API with the Agg canvas, so nothing touches global backend
state; OpenCV draws the boxes, Pillow writes the GIF.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.eval.rollout import FrameLog
from openfly_agent.rollout.record import EpisodeRecord

PREDICTED_COLOR = (255, 64, 32)  # RGB, the policy's box
TARGET_COLOR = (40, 220, 60)  # RGB, the ground-truth box of the target landmark


@dataclass(frozen=True)
class Footprint:
    """An axis-aligned building footprint in metres, for the map background."""

    xmin: float
    ymin: float
    xmax: float
    ymax: float
    height_m: float = 0.0
    landmark_id: str = ""
    kind: str = "building"  # building | tree


def safe_name(episode_id: str) -> str:
    """A file name for an episode id ('s/astar_data/low_short/t7' -> 's__astar_data__low_short__t7')."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", episode_id.replace("/", "__"))


def _view_box(record: EpisodeRecord, radius: float) -> tuple[float, float, float, float]:
    pts = np.concatenate([record.positions()[:, :2], np.asarray(record.reference_path)[:, :2]], axis=0)
    margin = radius + 30.0
    lo, hi = pts.min(axis=0) - margin, pts.max(axis=0) + margin
    half = float((hi - lo).max()) / 2.0  # square view, equal aspect
    cx, cy = (lo + hi) / 2.0
    return cx - half, cx + half, cy - half, cy + half


def plot_topdown(
    record: EpisodeRecord,
    path: str | Path,
    footprints: list[Footprint] | None = None,
    target_landmark_id: str | None = None,
    success_radius_m: float = C.SUCCESS_RADIUS_M,
    subtitle: str = "",
) -> Path:
    """Save a top-down map of one episode: buildings, ground-truth path, agent path, start, goal, collisions.

    Args:
        record: the finished episode.
        path: output PNG.
        footprints: building footprints (embedded scenes); the target landmark's is outlined.
        target_landmark_id: landmark to highlight.
        success_radius_m: radius of the circle drawn around the goal.
        subtitle: extra text under the title (e.g. the episode's metrics).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    fig = Figure(figsize=(6.4, 6.4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    x0, x1, y0, y1 = _view_box(record, success_radius_m)
    for fp in footprints or []:
        if fp.xmax < x0 or fp.xmin > x1 or fp.ymax < y0 or fp.ymin > y1:
            continue
        is_target = bool(target_landmark_id) and fp.landmark_id == target_landmark_id
        ax.add_patch(
            Rectangle(
                (fp.xmin, fp.ymin),
                fp.xmax - fp.xmin,
                fp.ymax - fp.ymin,
                facecolor="#f2b705" if is_target else "#b8b8b8",
                edgecolor="#333333" if is_target else "none",
                alpha=0.8,
                zorder=1,
            )
        )
    ref = np.asarray(record.reference_path, dtype=np.float64)
    pos = record.positions()
    goal = np.asarray(record.goal, dtype=np.float64)
    ax.plot(ref[:, 0], ref[:, 1], "--", color="#1a9850", lw=2, label="ground truth", zorder=3)
    ax.plot(
        pos[:, 0], pos[:, 1], "-", marker=".", ms=4, color="#2166ac", lw=1.5, label=record.policy, zorder=4
    )
    ax.add_patch(Circle((goal[0], goal[1]), success_radius_m, fill=False, ls=":", color="#1a9850", zorder=2))
    ax.scatter([pos[0, 0]], [pos[0, 1]], marker="o", s=60, color="black", label="start", zorder=5)
    ax.scatter([goal[0]], [goal[1]], marker="*", s=140, color="#1a9850", label="goal", zorder=5)
    ax.scatter([pos[-1, 0]], [pos[-1, 1]], marker="s", s=40, color="#2166ac", label="end", zorder=5)
    if record.collision_steps:
        hits = pos[[s + 1 for s in record.collision_steps]]
        ax.scatter(hits[:, 0], hits[:, 1], marker="x", s=70, color="#d73027", label="collision", zorder=6)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, east)")
    ax.set_ylabel("y (m, north)")
    ax.set_title(f"{record.episode_id}\n{subtitle}" if subtitle else record.episode_id, fontsize=8)
    ax.legend(loc="upper right", fontsize=7)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def _draw_box(frame: np.ndarray, box: list[float] | None, color: tuple[int, int, int]) -> None:
    import cv2

    if box is None:
        return
    h, w = frame.shape[:2]
    cx, cy, bw, bh = box
    p0 = (int(round((cx - bw / 2) * w)), int(round((cy - bh / 2) * h)))
    p1 = (int(round((cx + bw / 2) * w)), int(round((cy + bh / 2) * h)))
    cv2.rectangle(frame, p0, p1, color, max(1, w // 112))


def annotate_frames(frames: FrameLog, actions: list[int]) -> list[np.ndarray]:
    """Copies of the frames with the target box (green), the predicted box (red) and the step's action."""
    import cv2

    out = []
    for t, frame in enumerate(frames.frames):
        img = np.ascontiguousarray(frame.copy())
        _draw_box(img, frames.target_boxes[t], TARGET_COLOR)
        _draw_box(img, frames.predicted_boxes[t], PREDICTED_COLOR)
        label = f"{t}: {C.ACTION_NAMES.get(actions[t], '?')}" if t < len(actions) else str(t)
        scale = max(0.3, img.shape[1] / 448)
        cv2.putText(
            img,
            label,
            (3, int(14 * scale * 2)),
            cv2.FONT_HERSHEY_SIMPLEX,
            scale,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
        out.append(img)
    return out


def write_gif(frames: FrameLog, actions: list[int], path: str | Path, frame_ms: int = 250) -> Path:
    """Write the annotated egocentric frames of one episode as an animated GIF (loops forever)."""
    from PIL import Image

    images = [Image.fromarray(f) for f in annotate_frames(frames, actions)]
    if not images:
        raise ValueError(f"no frames to write to {path}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=frame_ms, loop=0)
    return path

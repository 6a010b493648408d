"""Render every kept frame of a trajectory through a Simulator and read the landmark boxes.

Simulators with a stateless `render(scene_id, pose, pitch_deg)` (the embedded one) are asked frame by frame;
any other `Simulator` is reset to the start pose and stepped through the actions (the motion then comes from
the same `sim/dynamics.py`, so the frames show the same poses).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from openfly_agent.sim.base import EpisodeSpec, Simulator
from openfly_agent.utils.geometry import Pose


@dataclass
class RenderedFrames:
    frames: list[np.ndarray]  # (H, W, 3) uint8 RGB per kept frame
    boxes: list[
        dict[str, np.ndarray]
    ]  # per frame: landmark id -> (4,) (cx, cy, w, h) of every visible landmark


def render_poses(
    sim: Simulator,
    scene_id: str,
    poses: list[Pose],
    pitch_deg: float,
    actions: np.ndarray | None = None,
    min_box_pixels: int = 0,
) -> RenderedFrames:
    """Frames and boxes at `poses` (one per kept frame).

    Args:
        sim: any Simulator; its `render` method is used when it has one.
        scene_id: e.g. "embedded-3".
        poses: T poses.
        pitch_deg: camera pitch for the whole trajectory.
        actions: (T,) labels; needed only for simulators without `render` (stepped from poses[0]).
        min_box_pixels: boxes covering fewer pixels count as not visible.
    """
    if hasattr(sim, "render"):
        observations = [sim.render(scene_id, pose, pitch_deg) for pose in poses]
    else:
        if actions is None or len(actions) != len(poses):
            raise ValueError("a simulator without render() needs the trajectory's actions (one per pose)")
        spec = EpisodeSpec(episode_id="toolchain", scene_id=scene_id, start=poses[0], pitch_deg=pitch_deg)
        observations = [sim.reset(spec)]
        for action in actions[:-1]:
            observations.append(sim.step(int(action))[0])
    frames = [np.ascontiguousarray(obs.rgb) for obs in observations]
    boxes = []
    for obs in observations:
        h, w = obs.rgb.shape[:2]
        found = {}
        for landmark_id, box in (obs.boxes or {}).items():
            box = np.asarray(box, dtype=np.float64)
            if box[2] * box[3] * w * h >= min_box_pixels:
                found[landmark_id] = box
        boxes.append(found)
    return RenderedFrames(frames, boxes)


def target_boxes(rendered: RenderedFrames, landmark_id: str) -> tuple[np.ndarray, np.ndarray]:
    """(T, 4) boxes of one landmark (zeros where invisible) and (T,) visibility."""
    return leg_target_boxes(rendered, [landmark_id], [len(rendered.boxes)])


def leg_of_frame(leg_end_frames: list[int], t: int) -> int:
    """The leg frame t belongs to: the first whose end frame is after t; the last leg from its own end on (the
    STOP frame). A leg's end frame belongs to the next leg, whose first decision it is."""
    return next((k for k, end in enumerate(leg_end_frames) if end > t), len(leg_end_frames) - 1)


def leg_target_boxes(
    rendered: RenderedFrames, target_ids: list[str], leg_end_frames: list[int]
) -> tuple[np.ndarray, np.ndarray]:
    """(T, 4) boxes of the current leg's target at each frame (zeros where invisible) and (T,) visibility; one
    target id per leg, in route order."""
    if len(target_ids) != len(leg_end_frames):
        raise ValueError(f"{len(target_ids)} targets for {len(leg_end_frames)} legs: one target per leg")
    boxes = np.zeros((len(rendered.boxes), 4), dtype=np.float64)
    visible = np.zeros(len(rendered.boxes), dtype=bool)
    for t, frame_boxes in enumerate(rendered.boxes):
        landmark_id = target_ids[leg_of_frame(leg_end_frames, t)]
        if landmark_id in frame_boxes:
            boxes[t], visible[t] = frame_boxes[landmark_id], True
    return boxes, visible

"""Top-down plots and GIFs: files are written, boxes land where they should, samples are stable."""

from __future__ import annotations

import numpy as np
from PIL import Image

from openfly_agent.eval.outputs import sample_for_plots
from openfly_agent.eval.plots import Footprint, annotate_frames, plot_topdown, safe_name, write_gif
from openfly_agent.eval.rollout import FrameLog
from openfly_agent.rollout.record import EpisodeRecord


def _record(episode_id="embedded-3/astar_data/low_short/t1", split="test_seen"):
    return EpisodeRecord(
        split=split,
        episode_id=episode_id,
        scene_id="embedded-3",
        policy="agent",
        instruction="go",
        goal=[30.0, 0.0, 20.0],
        reference_path=[[0.0, 0.0, 20.0], [30.0, 0.0, 20.0]],
        actions=[1, 1, 1, 0],
        poses=[[3.0 * min(i, 3), 0.0, 20.0, 0.0] for i in range(5)],
        stopped=True,
        end_reason="stop",
        collision_steps=[1],
    )


def test_topdown_plot_is_written(tmp_path):
    footprints = [Footprint(40, -10, 60, 10, 50.0, "b1"), Footprint(900, 900, 950, 950, 10.0, "far")]
    path = plot_topdown(
        _record(), tmp_path / "p" / "x.png", footprints, target_landmark_id="b1", subtitle="SR 1"
    )
    image = np.asarray(Image.open(path))
    assert image.shape[0] == 640 and image.shape[1] == 640
    assert (np.abs(np.diff(image[..., :3].astype(int), axis=0)).sum()) > 0  # not blank


def test_gif_frames_show_both_boxes(tmp_path):
    frames = FrameLog(
        frames=[np.zeros((64, 64, 3), np.uint8) for _ in range(3)],
        predicted_boxes=[[0.5, 0.5, 0.5, 0.5], None, [0.25, 0.25, 0.25, 0.25]],
        target_boxes=[None, [0.5, 0.5, 1.0, 1.0], None],
    )
    annotated = annotate_frames(frames, [1, 2, 0])
    # Predicted box of frame 0: x from 16 to 48 px; the red edge at column 16, the centre untouched.
    assert tuple(annotated[0][32, 16]) == (255, 64, 32) and annotated[0][32, 32].sum() == 0
    assert (annotated[1][..., 1] == 220).any()  # green target box
    assert not (annotated[1] == (255, 64, 32)).all(axis=-1).any()  # no predicted box on frame 1
    path = write_gif(frames, [1, 2, 0], tmp_path / "g.gif")
    gif = Image.open(path)
    assert gif.n_frames == 3


def test_plot_samples_are_evenly_spaced_per_split():
    records = [_record(f"s/a/b/t{i:02d}") for i in range(10)] + [_record("u/a/b/t0", "test_unseen")]
    picked = sample_for_plots(records, 3)
    assert [r.episode_id for r in picked] == ["s/a/b/t00", "s/a/b/t04", "s/a/b/t09", "u/a/b/t0"]
    assert sample_for_plots(records, 0) == []
    assert safe_name("embedded-3/astar_data/low short/t1") == "embedded-3__astar_data__low_short__t1"

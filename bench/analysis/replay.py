"""Stored eval.py flights rendered again: each flight with its dataset episode, in the dataset's embedded cities,
at the camera pitch it was flown with (bench/stop_landmarks.py, bench/leg_boxes.py).

eval.py renders each episode at its own pitch (a share of the generated routes fly pitched 45 deg down); a frame
rendered again at another pitch holds other boxes, so every re-render of a stored flight goes through `render_at`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

from openfly_agent.data.schema import Episode
from openfly_agent.eval.compare import load_policy_folder
from openfly_agent.eval.config import EvalConfig
from openfly_agent.eval.factory import embedded_sim_config, load_full_splits
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.sim.base import Pose
from openfly_agent.sim.embedded import EmbeddedSimulator


@contextmanager
def replayed_flights(
    policy_dir: str,
    dataset_root: str,
    split: str,
    keep: Callable[[EpisodeRecord], bool] | None = None,
    kept: str = "",
) -> Iterator[tuple[EmbeddedSimulator, list[tuple[EpisodeRecord, Episode]]]]:
    """The flights of `split` in `policy_dir` (those `keep` accepts, described by `kept` in the error when none
    is left), each with its episode of `dataset_root`, and a simulator of the dataset's cities to render them in.
    A flight whose episode is not in the dataset stops the command with its id."""
    cfg = EvalConfig(checkpoint="unused", dataset_root=dataset_root, split=[split])
    episodes = {e.episode_id: e for e in load_full_splits(cfg)[split]}
    records = [
        r for r in load_policy_folder(policy_dir).records if r.split == split and (keep is None or keep(r))
    ]
    if not records:
        raise SystemExit(f"{policy_dir}: no flight of split {split}{' ' + kept if kept else ''}")
    flights = []
    for record in records:
        episode = episodes.get(record.episode_id)
        if episode is None:
            raise SystemExit(f"{policy_dir}: episode {record.episode_id} is not in {dataset_root} ({split})")
        flights.append((record, episode))
    with EmbeddedSimulator(embedded_sim_config(cfg, list(episodes.values()))) as sim:
        yield sim, flights


def render_at(
    sim: EmbeddedSimulator, record: EpisodeRecord, episode: Episode, poses: Sequence[Sequence[float]]
):
    """The observations at the flight's `poses` ((x, y, z, yaw) each), at the pitch its episode was flown with."""
    return sim.render_many(record.scene_id, [Pose(*pose) for pose in poses], episode.pitch_deg)

"""Files a finished evaluation leaves behind: results JSON / Markdown, the policy comparison, plots.

<output_dir>/<policy>/results.json, results.md, episodes.jsonl, plots/<split>/*.png, gifs/*.gif
<output_dir>/summary.json, summary.md
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.schema import Episode
from openfly_agent.eval.config import AGENT_POLICIES, EvalConfig
from openfly_agent.eval.plots import plot_topdown, safe_name
from openfly_agent.eval.report import (
    INTERVAL_NOTE,
    comparison_markdown,
    outcomes_markdown,
    policy_results,
    results_markdown,
)
from openfly_agent.eval.scene_map import FootprintCache
from openfly_agent.rollout.episodes import target_landmark
from openfly_agent.rollout.metrics import episode_metrics, trajectory_of
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.utils.files import write_text_atomic

logger = logging.getLogger(__name__)

SUMMARY_JSON = "summary.json"
SUMMARY_MD = "summary.md"


def run_meta(cfg: EvalConfig, policy: str, split_sizes: dict[str, int] | None = None) -> dict:
    """Settings recorded next to the numbers; `split_episodes`: each split's episodes before `max_episodes`
    (a card says "40 of 520 episodes" from it)."""
    return {
        "checkpoint": cfg.checkpoint if policy in AGENT_POLICIES else None,
        "dataset_root": cfg.dataset_root,
        "sim": cfg.sim.type,
        "max_steps": cfg.max_steps,
        "batch_size": cfg.batch_size,
        "seed": cfg.seed,
        "unnorm_key": cfg.agent.unnorm_key if policy in AGENT_POLICIES else None,
        "memory_probe": cfg.agent.memory_probe if policy in AGENT_POLICIES else None,
        "max_episodes": cfg.max_episodes,
        "split_episodes": dict(split_sizes or {}),
    }


def sample_for_plots(records: list[EpisodeRecord], count: int) -> list[EpisodeRecord]:
    """`count` records per split, evenly spaced over the sorted episode ids (the same for every policy)."""
    picked = []
    for split in dict.fromkeys(r.split for r in records):
        subset = sorted((r for r in records if r.split == split), key=lambda r: r.episode_id)
        if count and subset:
            index = np.unique(np.linspace(0, len(subset) - 1, min(count, len(subset))).round().astype(int))
            picked += [subset[i] for i in index]
    return picked


def _subtitle(record: EpisodeRecord, profiles: list[str]) -> str:
    parts = []
    for profile in profiles:
        m = episode_metrics(trajectory_of(record), profile)
        parts.append(f"{profile}: NE {m['ne']:.1f} m, SR {int(m['success'])}, SPL {m['spl']:.2f}")
    return " | ".join(parts) + f" | end: {record.end_reason}"


def write_plots(
    cfg: EvalConfig,
    records: list[EpisodeRecord],
    folder: Path,
    episodes: dict[tuple[str, str], Episode],
    city_config=None,
) -> list[Path]:
    """Top-down plots of a sample of episodes into `folder/plots/<split>/` (`city_config`: embedded)."""
    footprints_of = FootprintCache(city_config)
    paths = []
    for record in sample_for_plots(records, cfg.plots):
        episode = episodes.get(record.key)
        footprints = footprints_of(record.scene_id) if cfg.sim.type == "embedded" else []
        out = folder / "plots" / record.split / f"{safe_name(record.episode_id)}.png"
        paths.append(
            plot_topdown(
                record,
                out,
                footprints,
                target_landmark_id=target_landmark(episode) if episode else None,
                subtitle=_subtitle(record, cfg.profiles),
            )
        )
    return paths


def write_policy_outputs(
    cfg: EvalConfig,
    policy: str,
    records: list[EpisodeRecord],
    folder: Path,
    episodes_by_split: dict[str, list[Episode]],
    city_config=None,
    split_sizes: dict[str, int] | None = None,
) -> dict:
    """results.json + results.md (+ plots) of one policy, all computed from `records`; returns the results.

    `city_config` is the `CityConfig` of the embedded scenes (building footprints on the plots); `split_sizes`
    the episodes of each split before `max_episodes` (recorded in the results' meta).
    """
    results = policy_results(policy, records, cfg.profiles, run_meta(cfg, policy, split_sizes))
    write_text_atomic(folder / C.RESULTS_JSON, json.dumps(results, indent=2) + "\n")
    write_text_atomic(folder / C.RESULTS_MD, results_markdown(results) + "\n")
    if cfg.plots:
        episodes = {(split, e.episode_id): e for split, eps in episodes_by_split.items() for e in eps}
        write_plots(cfg, records, folder, episodes, city_config)
    return results


def write_summary(cfg: EvalConfig, all_results: list[dict], root: Path) -> str:
    """summary.md / summary.json comparing every policy of the run; returns the Markdown."""
    text = "## Closed-loop evaluation (overall, per split and metric profile)\n\n" + INTERVAL_NOTE + "\n\n"
    text += comparison_markdown(all_results, cfg.profiles)
    text += "\n" + outcomes_markdown(all_results, cfg.profiles)
    text += f"\nPer-scene tables: {root}/<policy>/results.md; plots: {root}/<policy>/plots/\n"
    write_text_atomic(root / SUMMARY_MD, text)
    summary = {
        r["policy"]: {s: {p: t["overall"] for p, t in tables.items()} for s, tables in r["splits"].items()}
        for r in all_results
    }
    write_text_atomic(root / SUMMARY_JSON, json.dumps(summary, indent=2) + "\n")
    return text

"""The statistics the paper reports about its data, from the unit ledgers: JSON and plots.

Trajectory count (per split, scene, category), vocabulary size, path and instruction length, action
histogram, flight height distribution, how many route attempts each filter rejected, landmarks per route, and
how often the landmark the instruction is talking about is out of view (toolchain/visibility.py).
"""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.toolchain.ledger import STATUS_OK, UnitLedger

_WORD = re.compile(r"[a-z]+(?:[-'][a-z]+)*")


def _describe(values) -> dict:
    values = np.asarray(list(values), dtype=np.float64)
    if values.size == 0:
        return {"count": 0}
    return {
        "count": int(values.size),
        "mean": float(values.mean()),
        "median": float(np.median(values)),
        "p90": float(np.percentile(values, 90)),
        "min": float(values.min()),
        "max": float(values.max()),
    }


def words_of(text: str) -> list[str]:
    """Lower-case word tokens ("U-turn" is one word)."""
    return _WORD.findall(text.lower())


def _share(part: int, whole: int) -> float | None:
    return part / whole if whole else None


def visibility_summary(records: list[dict]) -> dict:
    """The counts of `visibility.route_visibility`, pooled over the A* records that carry them.

    clause_hidden_share (clause_unseen_share): of the decision steps whose current instruction clause names a
    landmark, the share at which that landmark is not in the frame (or too small to be seen);
    leg_hidden_share (leg_unseen_share): of all decision steps, the share at which the current leg's target is
    not; targets_named_share: of the routes, those whose instruction names every target in order.
    """
    rows = [r for r in records if "decision_steps" in r]
    keys = ("decision_steps", "clause_steps", "clause_hidden", "clause_unseen", "leg_hidden", "leg_unseen")
    total = {k: sum(int(r[k]) for r in rows) for k in keys}
    return {
        "routes": len(rows),
        **total,
        "clause_hidden_share": _share(total["clause_hidden"], total["clause_steps"]),
        "clause_unseen_share": _share(total["clause_unseen"], total["clause_steps"]),
        "leg_hidden_share": _share(total["leg_hidden"], total["decision_steps"]),
        "leg_unseen_share": _share(total["leg_unseen"], total["decision_steps"]),
        "targets_named_share": _share(sum(int(r["targets_named"]) for r in rows), len(rows)),
    }


def summarize_records(records: list[dict], height_bin_m: float = 10.0) -> dict:
    """The summary of ledger records (see the module docstring)."""
    ok = [r for r in records if r.get("status") == STATUS_OK]
    rejected = Counter(r.get("reason", "unknown") for r in records if r.get("status") != STATUS_OK)
    instructions = [r.get("instruction", "") for r in ok]
    vocabulary = set().union(*[set(words_of(t)) for t in instructions]) if instructions else set()
    actions = Counter(int(a) for r in ok for a in r.get("actions", []))
    heights = [r["flight_height_m"] for r in ok if "flight_height_m" in r]
    top = max(heights, default=0.0)
    edges = np.arange(0.0, top + height_bin_m, height_bin_m) if heights else np.array([0.0, height_bin_m])
    counts, edges = np.histogram(heights, bins=edges)
    return {
        "trajectories": len(ok),
        "attempts": len(records),
        "rejected": dict(sorted(rejected.items())),
        "per_split": dict(sorted(Counter(r["split"] for r in ok).items())),
        "per_scene": dict(sorted(Counter(r["scene_id"] for r in ok).items())),
        "per_category": dict(sorted(Counter(r["category"] for r in ok).items())),
        "dagger_episodes": sum(1 for r in ok if r.get("kind") == "dagger"),
        "vocabulary_size": len(vocabulary),
        "instruction_words": _describe(len(words_of(t)) for t in instructions),
        "path_length_m": _describe(r["path_length_m"] for r in ok if "path_length_m" in r),
        "actions_per_trajectory": _describe(len(r.get("actions", [])) for r in ok),
        "landmarks_per_route": dict(
            sorted(Counter(str(r["landmarks"]) for r in ok if "landmarks" in r).items())
        ),
        "visibility": visibility_summary(ok),
        "action_histogram": {C.ACTION_NAMES[a]: actions[a] for a in sorted(actions)},
        "flight_height_m": {
            **_describe(heights),
            "histogram": {"edges": edges.tolist(), "counts": counts.tolist()},
        },
    }


def empty_splits_message(summary: dict) -> str | None:
    """One line naming the splits of a summary that hold no trajectory (eval stops on them), with the settings
    that fill each; None when every split has some. The `val` split is optional (training falls back to
    test_seen without it), so it is not named."""
    hints = {  # what puts trajectories in each split
        C.SPLIT_TRAIN: "--scenes.train_seeds",
        C.SPLIT_TEST_SEEN: "--scenes.test_seen_fraction or --scenes.trajectories_per_scene",
        C.SPLIT_TEST_UNSEEN: "--scenes.unseen_seeds",
    }
    empty = [split for split in hints if not summary["per_split"].get(split)]
    if not empty:
        return None
    fixes = ", ".join(f"{split} with {hints[split]}" for split in empty)
    return f"split(s) {', '.join(empty)} came out empty (0 trajectories), and eval stops on an empty split: fill {fixes}"


def plot_summary(summary: dict, records: list[dict], path: Path) -> None:
    """Six panels: actions, path length, instruction length, flight height, categories, splits."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in records if r.get("status") == STATUS_OK]
    fig, axes = plt.subplots(2, 3, figsize=(15, 8))
    panels = [
        ("actions", list(summary["action_histogram"]), list(summary["action_histogram"].values())),
        ("categories", list(summary["per_category"]), list(summary["per_category"].values())),
        ("splits", list(summary["per_split"]), list(summary["per_split"].values())),
    ]
    for ax, (title, names, values) in zip([axes[0, 0], axes[1, 1], axes[1, 2]], panels):
        ax.bar(range(len(values)), values, color="tab:blue")
        ax.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=8)
        ax.set_title(f"{title} (count)")
    for ax, key, label in (
        (axes[0, 1], "path_length_m", "path length (m)"),
        (axes[0, 2], "instruction", "instruction length (words)"),
    ):
        values = [len(words_of(r["instruction"])) if key == "instruction" else r[key] for r in ok]
        ax.hist(values, bins=30, color="tab:green")
        ax.set_title(label)
    hist = summary["flight_height_m"]["histogram"]
    axes[1, 0].stairs(hist["counts"], hist["edges"], fill=True, color="tab:orange")
    axes[1, 0].set_title("flight height above ground (m)")
    fig.suptitle(f"{summary['trajectories']} trajectories, vocabulary {summary['vocabulary_size']} words")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_summary(root: str | Path, plots: bool = True) -> dict:
    """Summarise every ledger under `root`, write `meta/toolchain/summary.json` (+ `.png`), return it."""
    root = Path(root)
    records = UnitLedger(root).read_all()
    summary = summarize_records(records)
    path = root / C.TOOLCHAIN_SUMMARY_JSON
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    if plots and records:
        plot_summary(summary, records, root / C.TOOLCHAIN_SUMMARY_PNG)
    return summary

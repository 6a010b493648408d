"""Where a trained agent's target boxes go wrong, on a test split's visible target boxes.

The offline `box_iou` of a run (training/evaluate.py) is one mean. This breaks it down: IoU by the target's share of
the frame and by how far its centre is from the frame's vertical midline, how often the predicted centre falls
inside the target box, the error of the predicted size, whether the most likely cell of the head's grid is the one
holding the target's centre, and the IoU that an exact centre (the predicted size kept) or an exact size (the
predicted centre kept) would give. Read it to choose the next grounding lever: resolution for small far targets,
the head's size branch, views with the target off-centre, or the landmark choice itself.

    python bench/grounding_errors.py --run outputs/recipe/grounding
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import torch

from openfly_agent import constants as C
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.grounding.head import CellGroundingHead, box_cells, iou_and_giou
from openfly_agent.model.persistence.checkpoint_path import resolve_checkpoint_folder
from openfly_agent.training.builder import load_splits
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.ema import load_live_weights
from openfly_agent.training.evaluate import eval_indices
from openfly_agent.training.stages import stage_data
from openfly_agent.utils.config import config_from_dict, replace

logger = logging.getLogger(__name__)

AREA_EDGES = (0.0, 0.02, 0.06, 0.15, 0.4, 1.0)  # target box area as a fraction of the frame
OFFSET_EDGES = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)  # |cx - 0.5| of the target box, a fraction of the frame's width


@dataclass
class TargetBoxes:
    """The head's predictions on a split's samples, kept where the target is visible."""

    pred: torch.Tensor  # (N, 4) cxcywh, visible targets only
    target: torch.Tensor  # (N, 4) cxcywh
    cell_logits: torch.Tensor | None  # (N, P) when the head scores cells
    split: str  # the split read
    samples: int  # samples read, visible target or not
    visibility_accuracy: float  # the visibility logit's sign against the truth, over every sample read


def _mean(values: torch.Tensor) -> float:
    return float(values.float().mean()) if values.numel() else float("nan")


def centre_inside(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the centre of each predicted box lies strictly inside its target box ((N, 4) cxcywh each)."""
    return ((pred[:, 0] - target[:, 0]).abs() < target[:, 2] / 2) & (
        (pred[:, 1] - target[:, 1]).abs() < target[:, 3] / 2
    )


def grounding_errors(
    pred: torch.Tensor,
    target: torch.Tensor,
    cell_logits: torch.Tensor | None = None,
    area_edges: tuple[float, ...] = AREA_EDGES,
    offset_edges: tuple[float, ...] = OFFSET_EDGES,
) -> dict:
    """The breakdown of module docstring for (N, 4) cxcywh predictions of (N, 4) visible target boxes.

    Args:
        pred: predicted boxes.
        target: true boxes (all visible).
        cell_logits: (N, P) the head's per-cell logits on its square grid, if it scores cells.
        area_edges: edges of the target-area bins (fractions of the frame, increasing; the last bin is closed).
        offset_edges: edges of the bins of the target centre's horizontal offset from the frame's centre,
            |cx - 0.5| (increasing; the last bin is closed).

    Returns:
        A JSON-ready dict: `count`, `mean_iou`, `iou_at_least_0_5`, `iou_zero`, `centre_inside`,
        `iou_centre_inside` / `iou_centre_outside`, `log_area_ratio` (mean of log(pred area / target area)) and
        its absolute mean, `iou_true_centre`, `iou_true_size`, `cell_exact` / `cell_within_one` (argmax cell
        against the target centre's cell, Chebyshev distance; with cell logits), `by_area`, one entry per bin
        (`area_min`, `area_max`, `count`, `mean_iou`, `centre_inside`), and `by_offset`, the same per offset bin
        (`offset_min`, `offset_max`, ...). Means over an empty set are NaN.
    """
    pred, target = pred.float(), target.float()
    iou, _ = iou_and_giou(pred, target)  # (N,)
    inside = centre_inside(pred, target)
    area_pred, area_target = pred[:, 2] * pred[:, 3], target[:, 2] * target[:, 3]
    log_ratio = torch.log(area_pred.clamp(min=1e-9) / area_target.clamp(min=1e-9))
    true_centre, _ = iou_and_giou(torch.cat([target[:, :2], pred[:, 2:]], dim=-1), target)
    true_size, _ = iou_and_giou(torch.cat([pred[:, :2], target[:, 2:]], dim=-1), target)
    errors = {
        "count": int(target.shape[0]),
        "mean_iou": _mean(iou),
        "iou_at_least_0_5": _mean(iou >= 0.5),
        "iou_zero": _mean(iou == 0),
        "centre_inside": _mean(inside),
        "iou_centre_inside": _mean(iou[inside]),
        "iou_centre_outside": _mean(iou[~inside]),
        "log_area_ratio": _mean(log_ratio),
        "abs_log_area_ratio": _mean(log_ratio.abs()),
        "iou_true_centre": _mean(true_centre),
        "iou_true_size": _mean(true_size),
    }
    if cell_logits is not None:
        side = int(round(cell_logits.shape[-1] ** 0.5))
        predicted, true = cell_logits.argmax(dim=-1), box_cells(target, side)
        distance = torch.maximum(
            (predicted // side - true // side).abs(), (predicted % side - true % side).abs()
        )  # (N,) Chebyshev distance in cells
        errors.update(cell_exact=_mean(distance == 0), cell_within_one=_mean(distance <= 1))
    errors["by_area"] = _binned(area_target, area_edges, "area", iou, inside)
    errors["by_offset"] = _binned((target[:, 0] - 0.5).abs(), offset_edges, "offset", iou, inside)
    return errors


def _binned(
    values: torch.Tensor, edges: tuple[float, ...], name: str, iou: torch.Tensor, inside: torch.Tensor
) -> list[dict]:
    """Count, mean IoU and centre-inside share of the (N,) `values` in each bin of `edges` (the last one closed),
    as `<name>_min`, `<name>_max`, `count`, `mean_iou`, `centre_inside`."""
    bins = []
    for k, (low, high) in enumerate(zip(edges[:-1], edges[1:])):
        last = k == len(edges) - 2
        in_bin = (values >= low) & ((values <= high) if last else (values < high))
        bins.append(
            {
                f"{name}_min": low,
                f"{name}_max": high,
                "count": int(in_bin.sum()),
                "mean_iou": _mean(iou[in_bin]),
                "centre_inside": _mean(inside[in_bin]),
            }
        )
    return bins


def errors_markdown(errors: dict, title: str = "") -> str:
    """The breakdown as three markdown tables (the figures, then IoU by target area and by target offset)."""
    rows = [
        ("visible targets", f"{errors['count']}"),
        ("mean IoU", f"{errors['mean_iou']:.3f}"),
        ("IoU >= 0.5 / IoU = 0", f"{errors['iou_at_least_0_5']:.1%} / {errors['iou_zero']:.1%}"),
        ("predicted centre inside the target", f"{errors['centre_inside']:.1%}"),
        (
            "mean IoU, centre inside / outside",
            f"{errors['iou_centre_inside']:.3f} / {errors['iou_centre_outside']:.3f}",
        ),
        (
            "log(predicted / true area): mean / mean absolute",
            f"{errors['log_area_ratio']:+.2f} / {errors['abs_log_area_ratio']:.2f}",
        ),
        ("mean IoU with the true centre (predicted size)", f"{errors['iou_true_centre']:.3f}"),
        ("mean IoU with the true size (predicted centre)", f"{errors['iou_true_size']:.3f}"),
    ]
    if "cell_exact" in errors:
        rows.append(
            (
                "argmax cell: exact / within one cell",
                f"{errors['cell_exact']:.1%} / {errors['cell_within_one']:.1%}",
            )
        )
    lines = [f"### {title}", ""] if title else []
    lines += ["| figure | value |", "|---|---:|"] + [f"| {name} | {value} |" for name, value in rows]
    lines += _bins_table(errors["by_area"], "area", "target area (share of the frame)")
    lines += _bins_table(
        errors["by_offset"], "offset", "target centre's offset from the frame's centre, abs(cx - 0.5)"
    )
    return "\n".join(lines) + "\n"


def _bins_table(bins: list[dict], name: str, header: str) -> list[str]:
    """The markdown lines of one binned breakdown (`_binned`'s entries), after a blank line."""
    lines = ["", f"| {header} | targets | mean IoU | centre inside |", "|---|---:|---:|---:|"]
    for entry in bins:
        lines.append(
            f"| {entry[f'{name}_min']:g}-{entry[f'{name}_max']:g} | {entry['count']} | {entry['mean_iou']:.3f} "
            f"| {entry['centre_inside']:.1%} |"
        )
    return lines


@torch.no_grad()
def collect_target_boxes(
    run_dir: str | Path,
    checkpoint: str | Path | None = None,
    split: str | None = None,
    max_samples: int | None = 1024,
    batch_size: int = 32,
    centre_window: int | None | str = "checkpoint",
    live_weights: bool = False,
    data_root: str | Path | None = None,
) -> TargetBoxes:
    """Run a training run's agent over evenly spaced samples of a split and keep its target boxes.

    Args:
        run_dir: the training run (its `train_config.json` says the data, stage and history; relative paths in it
            are read from the current directory, as the run read them).
        checkpoint: the checkpoint to load (default: the run's last one).
        split: the split to read (default: the run's `data.test_split`).
        max_samples: evenly spaced samples of the split (None: all of them).
        batch_size: samples per forward.
        centre_window: the head's `grounding.centre_window` at inference (an int, or None for every cell);
            "checkpoint" keeps the checkpoint's.
        live_weights: score the live weights of the checkpoint's training state instead of its model folder's (which
            hold the weight average in a run with `optim.ema_decay`).
        data_root: read the split from this dataset (same layout) instead of the run's `data.root`, e.g. the same
            routes rendered with the camera turned aside (the run's extra train roots are then not read).

    Raises:
        FileNotFoundError: no `train_config.json` in `run_dir`, or no checkpoint.
        ValueError: the agent has no grounding head.
    """
    config_path = Path(run_dir) / C.TRAIN_CONFIG_NAME
    if not config_path.is_file():
        raise FileNotFoundError(f"{run_dir} is not a training run: no {C.TRAIN_CONFIG_NAME}")
    cfg = config_from_dict(TrainConfig, json.loads(config_path.read_text()))
    if split:
        cfg = replace(cfg, data=replace(cfg.data, test_split=split))
    if data_root:
        cfg = replace(cfg, data=replace(cfg.data, root=str(data_root), extra_train_roots=[]))
    folder = resolve_checkpoint_folder(checkpoint or run_dir)
    if folder is None:
        raise FileNotFoundError(f"no checkpoint at {checkpoint or run_dir}")
    agent = OpenFlyAgent.from_pretrained(str(folder)).eval()
    if live_weights:
        load_live_weights(agent, folder)
    if agent.network.grounding_head is None:
        raise ValueError(f"{folder}: the agent has no grounding head (model.grounding.type=none)")
    if centre_window != "checkpoint":
        if not isinstance(agent.network.grounding_head, CellGroundingHead):
            raise ValueError(
                f"{folder}: a centre window needs the cell grounding head (grounding.type=cells)"
            )
        agent.network.grounding_head.centre_window = centre_window
    data = stage_data(cfg, load_splits(cfg.data, cfg.model.grounding), agent)
    outputs = []
    hook = agent.network.grounding_head.register_forward_hook(
        lambda _module, _inputs, output: outputs.append(output)
    )
    preds, targets, cells, hits = [], [], [], 0  # visible targets only
    indices = eval_indices(len(data.test), max_samples)
    try:
        for first in range(0, len(indices), batch_size):
            batch = data.collate([data.test[i] for i in indices[first : first + batch_size]])
            agent(batch)
            output = outputs.pop()
            seen = batch[C.BOX_VISIBLE].bool()  # (B,)
            hits += int(((output.visibility > 0) == seen).sum())
            preds.append(output.boxes[seen])
            targets.append(batch[C.BOX].float()[seen])
            if output.cell_logits is not None:
                cells.append(output.cell_logits[seen])
    finally:
        hook.remove()
    pred, target = torch.cat([torch.zeros(0, 4), *preds]), torch.cat([torch.zeros(0, 4), *targets])
    logger.info(
        "%d of %d samples of %s have a visible target", len(target), len(indices), cfg.data.test_split
    )
    return TargetBoxes(
        pred=pred,
        target=target,
        cell_logits=torch.cat(cells) if cells else None,
        split=cfg.data.test_split,
        samples=len(indices),
        visibility_accuracy=hits / len(indices) if indices else float("nan"),
    )

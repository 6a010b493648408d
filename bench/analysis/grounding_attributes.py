"""Which landmark the grounding head picks when it misses, and which of the target's attributes its features hold.

Two measurements on a navigation run's test split (bench/grounding_attributes.py prints them):

- where the predicted centre lands (`centre_landing`): on the target's box, on an earlier landmark of the route,
  on another landmark of the frame, or on none; every sampled frame is rendered again by the embedded simulator
  for the boxes of all its landmarks. For the misses on another landmark: how often it shares the target's
  colour, type, size and feature, and how often the instruction names it (`named_in`).
- linear probes (`probe_accuracy`) of the target's colour and type, fit on train-split samples and scored on
  test ones, from three readings of the cell under the target's centre: its raw pixel statistics
  (`cell_colour_stats`), the vision backbone's token and the head's cell feature (the LLM's hidden state there,
  through the head's input projection); and from the head's query (the code that modulates every cell: what the
  head took from the instruction). With a colour vocabulary (`grounding.colour_vocabulary`), three readings more:
  the target cell's histogram of the named colours (and none), the colour the prompt's words name (its logits) and
  the class distribution that colour asks for. A probe at the majority rate means the reading does not hold the
  attribute.

Embedded-simulator datasets only (the boxes and the cities come from it).
"""

from __future__ import annotations

import json
import logging
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from openfly_agent import constants as C
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.grounding.head import CellGroundingHead
from openfly_agent.model.persistence.checkpoint_path import resolve_checkpoint_folder
from openfly_agent.model.vision.conv import cell_colour_stats, normalised_pixels
from openfly_agent.sim.embedded_scenes import EmbeddedScenes
from openfly_agent.sim.scene import Landmark
from openfly_agent.toolchain.grounding import source_render_settings
from openfly_agent.training.attribute_targets import ATTRIBUTE_FIELDS
from openfly_agent.training.builder import load_splits
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.evaluate import eval_indices
from openfly_agent.training.stages import stage_data
from openfly_agent.utils.config import config_from_dict
from openfly_agent.utils.geometry import Pose

logger = logging.getLogger(__name__)

LANDINGS = ("target", "earlier route landmark", "other landmark", "no landmark")
# with a colour vocabulary only
COLOUR_READINGS = (
    "colour vocabulary: cell histogram",
    "colour vocabulary: named colour",
    "colour vocabulary: ask",
)
READINGS = ("cell pixels", "backbone token", "head cell feature", "head query", *COLOUR_READINGS)
CELL_SCORES = ("cell score", "colour vocabulary: match term")  # the second with a colour vocabulary only


def centre_landing(
    centre: tuple[float, float], target_id: str, boxes: dict[str, np.ndarray], route_ids: list[str]
) -> tuple[str, str | None]:
    """(landing, landmark id) of a predicted centre among a frame's landmark boxes (cx, cy, w, h in [0, 1]).

    The target's box wins when the centre is inside it; otherwise an earlier landmark of the route, then any
    other landmark (the smallest box when several hold the centre: the nearer, occluding one is drawn over a
    farther one's box only where they overlap, and the smaller box is the tighter claim)."""

    def inside(box: np.ndarray) -> bool:
        return abs(centre[0] - box[0]) < box[2] / 2 and abs(centre[1] - box[1]) < box[3] / 2

    if target_id in boxes and inside(boxes[target_id]):
        return LANDINGS[0], target_id
    hits = sorted((boxes[k][2] * boxes[k][3], k) for k in boxes if k != target_id and inside(boxes[k]))
    route_hits = [k for _, k in hits if k in route_ids]
    if route_hits:
        return LANDINGS[1], route_hits[0]
    if hits:
        return LANDINGS[2], hits[0][1]
    return LANDINGS[3], None


def named_in(instruction: str, landmark: Landmark) -> bool:
    """Whether the instruction names the landmark by colour and type ("the red ... tower", within 25 characters)."""
    pattern = rf"\b{re.escape(landmark.color)}\b[^,.]{{0,25}}\b{re.escape(landmark.type)}\b"
    return re.search(pattern, instruction.lower()) is not None


def probe_accuracy(
    train_x: np.ndarray, train_y: list[str], test_x: np.ndarray, test_y: list[str], steps: int = 500
) -> tuple[float, float]:
    """(train, test) accuracy of a multinomial logistic regression (Adam, standardised inputs, weight decay)."""
    classes = {name: k for k, name in enumerate(sorted(set(train_y) | set(test_y)))}
    x_train, x_test = (
        torch.as_tensor(train_x, dtype=torch.float32),
        torch.as_tensor(test_x, dtype=torch.float32),
    )
    mean, std = x_train.mean(dim=0), x_train.std(dim=0) + 1e-6
    x_train, x_test = (x_train - mean) / std, (x_test - mean) / std
    y_train = torch.tensor([classes[y] for y in train_y])
    y_test = torch.tensor([classes[y] for y in test_y])
    generator = torch.Generator().manual_seed(0)
    linear = torch.nn.Linear(x_train.shape[1], len(classes))
    with torch.no_grad():
        linear.weight.copy_(torch.randn(linear.weight.shape, generator=generator) * 0.01)
        linear.bias.zero_()
    optimiser = torch.optim.Adam(linear.parameters(), lr=1e-2, weight_decay=1e-4)
    for _ in range(steps):
        optimiser.zero_grad()
        torch.nn.functional.cross_entropy(linear(x_train), y_train).backward()
        optimiser.step()
    with torch.no_grad():
        train_acc = (linear(x_train).argmax(dim=1) == y_train).float().mean().item()
        test_acc = (linear(x_test).argmax(dim=1) == y_test).float().mean().item()
    return train_acc, test_acc


@dataclass
class CellReadings:
    """The readings of the target's cell, the target's attributes (one row per visible target), the landings."""

    features: dict[str, list[np.ndarray]] = field(default_factory=lambda: {name: [] for name in READINGS})
    attributes: dict[str, list[str]] = field(default_factory=lambda: {name: [] for name in ATTRIBUTE_FIELDS})
    landings: Counter = field(default_factory=Counter)
    shared: Counter = field(default_factory=Counter)  # misses on another landmark: attributes shared, names
    # the target's cell's rank (cells scoring above it) under each score: the head's cell logits, and with a colour
    # vocabulary its match term alone
    cell_ranks: dict[str, list[int]] = field(default_factory=lambda: {name: [] for name in CELL_SCORES})


def cell_rank(logits: torch.Tensor, cell: int) -> int:
    """(P,) cell scores -> how many cells score above `cell` (0: it is the best)."""
    return int((logits > logits[cell]).sum())


def rank_summary(ranks: list[int]) -> dict[str, float]:
    """The share of frames whose target cell is the best cell and among the best 3, and the median rank (1 = the
    best), of `cell_rank` values."""
    values = np.asarray(ranks)
    return {
        "best": float(np.mean(values == 0)),
        "top 3": float(np.mean(values < 3)),
        "median": float(np.median(values)) + 1,
    }


class AttributeProbe:
    """Runs a navigation run's agent over its splits and gathers `CellReadings` (see the module docstring).

    Args:
        run_dir: a navigation-stage training run (its `train_config.json` names the datasets).
        checkpoint: the weights to read (default: the run's last checkpoint; any checkpoint of the same model,
            e.g. the grounding stage's).
        batch_size: samples per forward.
    """

    def __init__(
        self, run_dir: str | Path, checkpoint: str | Path | None = None, batch_size: int = 32
    ) -> None:
        config_path = Path(run_dir) / C.TRAIN_CONFIG_NAME
        if not config_path.is_file():
            raise FileNotFoundError(f"{run_dir} is not a training run: no {C.TRAIN_CONFIG_NAME}")
        cfg = config_from_dict(TrainConfig, json.loads(config_path.read_text()))
        folder = resolve_checkpoint_folder(checkpoint or run_dir)
        if folder is None:
            raise FileNotFoundError(f"no checkpoint at {checkpoint or run_dir}")
        self.agent = OpenFlyAgent.from_pretrained(str(folder)).eval()
        if not isinstance(self.agent.network.grounding_head, CellGroundingHead):
            raise ValueError(f"{folder}: the probe needs a grounding head with per-cell scores")
        self.data = stage_data(cfg, load_splits(cfg.data, cfg.model.grounding), self.agent)
        if not hasattr(self.data.test, "locate"):
            raise ValueError(
                f"{run_dir} is not a navigation-stage run: pass it with --checkpoint for other stages"
            )
        self.batch_size, self.grid = batch_size, self.agent.network.grounding_head.grid_side
        self.width, self.height, self.city_config = source_render_settings(cfg.data.root)
        self.cities = EmbeddedScenes(self.city_config)
        self._head_cells: list[torch.Tensor] = []
        self._queries: list[torch.Tensor] = []
        self._outputs: list = []

    @torch.no_grad()
    def read(self, split: str, max_samples: int | None, render: bool) -> CellReadings:
        """Readings of `max_samples` evenly spaced samples of "train" or "test" (with landings when `render`)."""
        dataset = self.data.train if split == "train" else self.data.test
        head = self.agent.network.grounding_head
        hooks = [
            head.register_forward_pre_hook(self._keep_head_cells, with_kwargs=True),
            head.cell_scorer.register_forward_pre_hook(lambda _m, args: self._queries.append(args[1])),
            head.register_forward_hook(lambda _m, _i, output: self._outputs.append(output)),
        ]
        sim = self._simulator() if render else None
        readings = CellReadings()
        indices = eval_indices(len(dataset), max_samples)
        try:
            for first in range(0, len(indices), self.batch_size):
                chunk = indices[first : first + self.batch_size]
                batch = self.data.collate([dataset[i] for i in chunk])
                self.agent(batch)
                output, head_cells = self._outputs.pop(), self._head_cells.pop()  # (B, P, d)
                queries = self._queries.pop()  # (B, d)
                tokens = self._backbone_tokens(batch[C.PIXEL_VALUES])  # (B, P, C) or None
                pixels = self._pixel_stats(batch[C.PIXEL_VALUES])  # (B, P, 18)
                # (B, P, C + 1) cell histograms and (B, C + 1) asks, or None
                histograms, asks = self._colour_vocabulary(batch[C.PIXEL_VALUES], output)
                for row, index in enumerate(chunk):
                    if bool(batch[C.BOX_VISIBLE][row]):
                        episode, t = dataset.locate(index)
                        box = batch[C.BOX][row].float()
                        cell = self._cell(box)
                        cells = {
                            "cell pixels": pixels[row, cell],
                            "backbone token": None if tokens is None else tokens[row, cell],
                            "head cell feature": head_cells[row, cell],
                            "head query": queries[row],
                            "colour vocabulary: cell histogram": None
                            if histograms is None
                            else histograms[row, cell],
                            "colour vocabulary: named colour": None
                            if output.word_colours is None
                            else output.word_colours[row],
                            "colour vocabulary: ask": None if asks is None else asks[row],
                        }
                        self._add(readings, episode, cells)
                        scores = {
                            "cell score": output.cell_logits,
                            "colour vocabulary: match term": output.match_logits,
                        }
                        for name, logits in scores.items():
                            if logits is not None:
                                readings.cell_ranks[name].append(cell_rank(logits[row], cell))
                        if sim is not None:
                            self._land(readings, sim, episode, t, output.boxes[row, :2].tolist())
        finally:
            for hook in hooks:
                hook.remove()
            if sim is not None:
                sim.close()
        return readings

    def _simulator(self):
        from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator  # lazy: the renderer

        return EmbeddedSimulator(
            EmbeddedSimConfig(width=self.width, height=self.height, city=self.city_config)
        )

    def _keep_head_cells(self, head, args, kwargs) -> None:
        hidden = args[0] if args else kwargs["hidden"]
        positions = kwargs.get("image_positions", args[2] if len(args) > 2 else None)  # (B, P)
        memory = head.input_proj(hidden.to(head.input_proj.weight.dtype))  # (B, L, d)
        self._head_cells.append(
            torch.gather(memory, 1, positions[..., None].expand(-1, -1, memory.shape[-1]))
        )

    def _backbone_tokens(self, pixels: torch.Tensor) -> torch.Tensor | None:
        return self.agent.network.vision_backbone(pixels)  # (B, P, C)

    def _colour_vocabulary(
        self, pixels: torch.Tensor, output
    ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """(B, P, C + 1) cell histograms of the named colours (and none) and the (B, C + 1) classes asked for by the
        colour its output's words name; (None, None) for a head without a colour vocabulary."""
        vocabulary = self.agent.network.grounding_head.colour_vocabulary
        if vocabulary is None:
            return None, None
        return vocabulary.histogram(pixels), vocabulary.ask(output.word_colours)

    def _pixel_stats(self, pixels: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) uint8 -> (B, P, 18) colour statistics of the token grid's cells."""
        x = normalised_pixels(pixels, torch.float32)
        cell = pixels.shape[-1] // self.grid
        return cell_colour_stats(x, cell).flatten(2).transpose(1, 2)

    def _cell(self, box: torch.Tensor) -> int:
        """Row-major index of the cell holding the box centre."""
        col = min(int(box[0] * self.grid), self.grid - 1)
        row = min(int(box[1] * self.grid), self.grid - 1)
        return row * self.grid + col

    def _add(self, readings: CellReadings, episode, cells: dict[str, torch.Tensor | None]) -> None:
        target = self.cities.landmarks(episode.scene_id).get(episode.landmark_ids[-1])
        if target is None:
            return
        for reading, values in cells.items():
            if values is not None:
                readings.features[reading].append(values.float().numpy())
        for name in ATTRIBUTE_FIELDS:
            readings.attributes[name].append(getattr(target, name))

    def _land(self, readings, sim, episode, t, centre) -> None:
        sim.register_city(self.cities.city(episode.scene_id))  # the city already generated for its landmarks
        x, y, z = (float(v) for v in episode.positions[t])
        observation = sim.render(episode.scene_id, Pose(x, y, z, float(episode.yaws[t])), episode.pitch_deg)
        target_id = episode.landmark_ids[-1]
        landing, hit = centre_landing(
            tuple(centre), target_id, observation.boxes or {}, list(episode.landmark_ids[:-1])
        )
        readings.landings[landing] += 1
        landmarks = self.cities.landmarks(episode.scene_id)
        if landing != LANDINGS[2] or target_id not in landmarks or hit not in landmarks:
            return
        readings.shared["misses"] += 1
        for name in ATTRIBUTE_FIELDS:
            readings.shared[name] += getattr(landmarks[hit], name) == getattr(landmarks[target_id], name)
        readings.shared["named in the instruction"] += named_in(episode.instruction, landmarks[hit])


def probe_table(train: CellReadings, test: CellReadings, attributes=("color", "type")) -> list[dict]:
    """One row per (reading, attribute): probe accuracy on train and test samples and the test majority rate."""
    rows = []
    for reading in READINGS:
        if not train.features[reading] or not test.features[reading]:
            continue
        for name in attributes:
            train_acc, test_acc = probe_accuracy(
                np.stack(train.features[reading]),
                train.attributes[name],
                np.stack(test.features[reading]),
                test.attributes[name],
            )
            majority = Counter(train.attributes[name]).most_common(1)[0][0]
            majority_rate = float(np.mean([y == majority for y in test.attributes[name]]))
            rows.append(
                {
                    "reading": reading,
                    "attribute": name,
                    "train": train_acc,
                    "test": test_acc,
                    "majority": majority_rate,
                }
            )
    return rows

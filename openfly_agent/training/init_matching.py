"""Start a stage from the previous one: load every checkpoint tensor whose name and shape the model shares.

The navigation stage starts from the grounding stage this way (and the model may gain modules between them,
e.g. the box token): what was loaded, what is new and what was left out is logged, never silently dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from safetensors import safe_open

from openfly_agent.model.persistence.checkpoint_path import checkpoint_files, resolve_checkpoint_folder


@dataclass
class MatchReport:
    """What `load_matching_weights` did with every tensor name."""

    loaded: list[str] = field(default_factory=list)  # model tensors filled from the checkpoint
    new: list[str] = field(default_factory=list)  # model tensors the checkpoint lacks (kept as initialised)
    reshaped: list[str] = field(default_factory=list)  # in both, with other shapes (kept as initialised)
    unused: list[str] = field(default_factory=list)  # checkpoint tensors the model lacks

    def summary(self, limit: int = 8) -> str:
        """One line for logs, naming up to `limit` keys of each non-loaded group."""

        def names(keys: list[str]) -> str:
            shown = ", ".join(keys[:limit]) + (
                f", ... ({len(keys) - limit} more)" if len(keys) > limit else ""
            )
            return f" [{shown}]" if keys else ""

        return (
            f"loaded {len(self.loaded)} tensors; new {len(self.new)}{names(self.new)}; "
            f"other shape {len(self.reshaped)}{names(self.reshaped)}; unused {len(self.unused)}{names(self.unused)}"
        )


def load_matching_weights(model: torch.nn.Module, checkpoint: str | Path) -> MatchReport:
    """Copy into `model` every tensor of `checkpoint` (a checkpoint folder, a run, its `last` pointer) whose
    name and shape match; the rest of `model` keeps its initialisation.

    Raises:
        FileNotFoundError: `checkpoint` is not a checkpoint folder or holds no weights.
    """
    folder = resolve_checkpoint_folder(checkpoint)
    if folder is None:
        raise FileNotFoundError(f"init.checkpoint {checkpoint} does not exist")
    expected = model.state_dict()
    report, matching = MatchReport(), {}
    seen: set[str] = set()
    for path in checkpoint_files(folder):
        with safe_open(str(path), framework="pt") as handle:  # safetensors: no unpickling
            for name in handle.keys():  # noqa: SIM118 (a safetensors handle is not iterable)
                seen.add(name)
                if name not in expected:
                    report.unused.append(name)
                    continue
                tensor = handle.get_tensor(name)
                if tuple(tensor.shape) != tuple(expected[name].shape):
                    report.reshaped.append(name)
                    continue
                matching[name] = tensor
                report.loaded.append(name)
    report.new = [name for name in expected if name not in seen]
    model.load_state_dict(matching, strict=False)
    for group in (report.loaded, report.new, report.reshaped, report.unused):
        group.sort()
    return report

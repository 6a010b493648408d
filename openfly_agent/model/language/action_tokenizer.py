"""Action ids <-> LLM token ids for the `discrete` head and the OpenVLA 8-dim `openvla_bins` head.

OpenVLA behaviour reproduced (docs/OFFICIAL_OPENFLY.md 3.6 and 11.1): 256 bin edges on [-1, 1] give
255 centres; encode = `vocab_end - digitize(clip(x))` (ids vocab_end-256 .. vocab_end-1); decode clips
`vocab_end - id - 1` to [0, 254] (the off-by-one at the edges: bins 1 and 256 decode to the outer centres).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from openfly_agent.constants import (
    MODEL_ACTION_IDS,
    NUM_ACTIONS,
    OPENVLA_ACTION_DIM,
    OPENVLA_ACTION_VECTORS,
)
from openfly_agent.model.config import (
    DECODE_EXACT,
    DECODE_NEAREST,
    DECODE_RULES,
    HEAD_DISCRETE,
    HEAD_OPENVLA_BINS,
    NUM_ACTION_SLOTS,
)

CODEBOOK = np.array([OPENVLA_ACTION_VECTORS[a] for a in MODEL_ACTION_IDS], dtype=np.float64)  # (10, 8)
# Per-dimension scale of the codebook, used by the `nearest` rule so a 15-unit turn code does not dominate.
_CODEBOOK_SCALE = np.maximum(np.abs(CODEBOOK).max(axis=0), 1.0)  # (8,)


class ActionTokenizer:
    """Maps OpenFly action ids 0..9 to the token ids the LLM predicts, and back.

    Args:
        head: `discrete` (action a -> id `vocab_end - 256 + a`, one token per step) or `openvla_bins`
            (the action's official 8-dim vector, q01/q99-normalised, one bin token per dim, then EOS).
        vocab_end: exclusive end of the 256 action ids (Llama-2: 32000, the ids overlap rare BPE tokens as in
            OpenVLA; the tiny preset reserves 256 ids after the tokenizer's vocabulary).
        eos_token_id: appended after the 8 bin tokens (`openvla_bins` only).
        action_stats: the `action` entry of one norm-stats profile (`q01`, `q99`, optional `mask`,
            `min`, `max`); needed by `openvla_bins`.
        decode_rule: `exact` (round, exact match with a codebook vector, else STOP: the official
            evaluation) or `nearest` (closest codebook vector after per-dimension scaling).
    """

    def __init__(
        self,
        head: str = HEAD_DISCRETE,
        vocab_end: int = NUM_ACTION_SLOTS,
        eos_token_id: int | None = None,
        action_stats: dict | None = None,
        decode_rule: str = DECODE_EXACT,
    ) -> None:
        if head not in (HEAD_DISCRETE, HEAD_OPENVLA_BINS):
            raise ValueError(
                f"action head {head!r} is not supported; use {HEAD_DISCRETE!r} or {HEAD_OPENVLA_BINS!r}"
            )
        if decode_rule not in DECODE_RULES:
            raise ValueError(f"decode_rule {decode_rule!r} is not supported; use one of {list(DECODE_RULES)}")
        if vocab_end < NUM_ACTION_SLOTS:
            raise ValueError(f"vocab_end={vocab_end} leaves no room for {NUM_ACTION_SLOTS} action ids")
        if head == HEAD_OPENVLA_BINS and eos_token_id is None:
            raise ValueError("the openvla_bins head appends EOS after the 8 bin tokens: pass eos_token_id")
        self.head = head
        self.vocab_end = int(vocab_end)
        self.eos_token_id = eos_token_id
        self.decode_rule = decode_rule
        self.action_stats = _check_stats(action_stats) if action_stats is not None else None
        self.bins = np.linspace(-1.0, 1.0, NUM_ACTION_SLOTS)  # 256 edges
        self.bin_centers = (self.bins[:-1] + self.bins[1:]) / 2.0  # 255 centres
        # the ids, fixed by vocab_end: resolved once here, read by every training and inference step
        self.action_token_begin = self.vocab_end - NUM_ACTION_SLOTS  # first of the 256 action ids
        # token id of each action 0..9 under the discrete head (logits are restricted to these)
        self.discrete_token_ids = tuple(self.action_token_begin + a for a in MODEL_ACTION_IDS)

    # --- ids --------------------------------------------------------------------------------------------

    @property
    def num_action_tokens(self) -> int:
        """Tokens generated per step (1 or 8; EOS excluded)."""
        return 1 if self.head == HEAD_DISCRETE else OPENVLA_ACTION_DIM

    def is_action_token(self, token_ids: np.ndarray) -> np.ndarray:
        """Mask of ids inside the 256-id action range."""
        token_ids = np.asarray(token_ids)
        return (token_ids >= self.action_token_begin) & (token_ids < self.vocab_end)

    # --- public API used by the collator and the agent ----------------------------------------------------
    def action_to_token_ids(self, action_id: int) -> list[int]:
        """Token ids appended after the prompt for action `action_id` (bins head: 8 tokens + EOS)."""
        _check_action(action_id)
        if self.head == HEAD_DISCRETE:
            return [self.action_token_begin + int(action_id)]
        vector = np.asarray(OPENVLA_ACTION_VECTORS[int(action_id)], dtype=np.float64)
        return [*self.vector_to_token_ids(self.normalize(vector)), int(self.eos_token_id)]

    def token_ids_to_action(self, token_ids: Sequence[int]) -> int:
        """Action id from generated token ids (discrete: 1 id; bins: the first 8 ids, EOS ignored)."""
        ids = np.asarray(list(token_ids), dtype=np.int64)
        if self.head == HEAD_DISCRETE:
            if ids.size < 1:
                raise ValueError("token_ids_to_action needs one token id for the discrete head")
            action = int(ids[0]) - self.action_token_begin
            if action not in MODEL_ACTION_IDS:
                raise ValueError(
                    f"token id {int(ids[0])} is not one of the discrete action ids {self.discrete_token_ids}"
                )
            return action
        if ids.size < OPENVLA_ACTION_DIM:
            raise ValueError(f"the openvla_bins head needs {OPENVLA_ACTION_DIM} token ids, got {ids.size}")
        return self.vector_to_action(self.unnormalize(self.token_ids_to_vector(ids[:OPENVLA_ACTION_DIM])))

    # --- bins -------------------------------------------------------------------------------------------
    def vector_to_token_ids(self, normalized: np.ndarray) -> list[int]:
        """Normalised vector in [-1, 1] -> bin token ids (`vocab_end - digitize`)."""
        clipped = np.clip(np.asarray(normalized, dtype=np.float64), -1.0, 1.0)
        discretized = np.digitize(clipped, self.bins)  # 1..256
        return [int(v) for v in self.vocab_end - discretized]

    def token_ids_to_vector(self, token_ids: np.ndarray) -> np.ndarray:
        """Bin token ids -> normalised bin centres (OpenVLA's clip to [0, 254])."""
        discretized = self.vocab_end - np.asarray(token_ids, dtype=np.int64)
        index = np.clip(discretized - 1, 0, self.bin_centers.shape[0] - 1)
        return self.bin_centers[index]

    def normalize(self, vector: np.ndarray) -> np.ndarray:
        """BOUNDS_Q99: `clip(2 (x - q01) / (q99 - q01 + 1e-8) - 1, -1, 1)` where masked; 0 on flat dims."""
        stats = self._stats()
        q01, q99, mask = stats["q01"], stats["q99"], stats["mask"]
        out = np.where(mask, np.clip(2.0 * (vector - q01) / (q99 - q01 + 1e-8) - 1.0, -1.0, 1.0), vector)
        if "min" in stats and "max" in stats:
            out = np.where(stats["min"] == stats["max"], 0.0, out)
        return out

    def unnormalize(self, normalized: np.ndarray) -> np.ndarray:
        """`0.5 (a + 1) (q99 - q01) + q01` where masked (predict_action)."""
        stats = self._stats()
        q01, q99, mask = stats["q01"], stats["q99"], stats["mask"]
        return np.where(mask, 0.5 * (normalized + 1.0) * (q99 - q01) + q01, normalized)

    def vector_to_action(self, vector: np.ndarray) -> int:
        """Un-normalised 8-dim vector -> action id by the configured decode rule."""
        vector = np.asarray(vector, dtype=np.float64)
        if self.decode_rule == DECODE_NEAREST:
            distances = np.abs((CODEBOOK - vector[None]) / _CODEBOOK_SCALE).sum(axis=1)  # (10,)
            return int(np.argmin(distances))
        rounded = np.round(vector).astype(np.int64)
        for action in MODEL_ACTION_IDS:
            if np.array_equal(rounded, CODEBOOK[action].astype(np.int64)):
                return action
        return 0  # the official rule: anything that is not a codebook vector is STOP

    def _stats(self) -> dict:
        if self.action_stats is None:
            raise ValueError(
                "the openvla_bins head needs norm stats (q01 / q99 per dim): pass the dataset statistics "
                "(config.norm_stats / dataset_statistics.json) and choose action_head.unnorm_key"
            )
        return self.action_stats

    # --- persistence -------------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """JSON-friendly settings (norm stats live in config.json / dataset_statistics.json)."""
        return {
            "head": self.head,
            "vocab_end": self.vocab_end,
            "n_bins": NUM_ACTION_SLOTS,
            "eos_token_id": self.eos_token_id,
            "decode_rule": self.decode_rule,
            "action_token_begin": self.action_token_begin,
            "discrete_token_ids": list(self.discrete_token_ids),
        }

    def save(self, path: str | Path) -> None:
        """Write `to_dict()` as JSON (the checkpoint's action_tokenizer.json)."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")

    @classmethod
    def from_dict(cls, data: dict, action_stats: dict | None = None) -> ActionTokenizer:
        """Rebuild from `to_dict()` output."""
        return cls(
            head=data["head"],
            vocab_end=int(data["vocab_end"]),
            eos_token_id=data.get("eos_token_id"),
            action_stats=action_stats,
            decode_rule=data.get("decode_rule", DECODE_EXACT),
        )


def select_action_stats(norm_stats: dict | None, unnorm_key: str | None) -> dict | None:
    """The `action` stats of profile `unnorm_key` (None: the only profile); None without any stats."""
    if not norm_stats:
        return None
    if unnorm_key is None:
        if len(norm_stats) != 1:
            raise ValueError(
                f"norm_stats holds {len(norm_stats)} profiles {sorted(norm_stats)}: "
                "set action_head.unnorm_key"
            )
        unnorm_key = next(iter(norm_stats))
    if unnorm_key not in norm_stats:
        raise ValueError(f"action_head.unnorm_key={unnorm_key!r} is not in norm_stats {sorted(norm_stats)}")
    profile = norm_stats[unnorm_key]
    if "action" not in profile:
        raise ValueError(f"norm_stats[{unnorm_key!r}] has no 'action' entry (keys: {sorted(profile)})")
    return profile["action"]


def _check_stats(stats: dict) -> dict:
    out = {}
    for key in ("q01", "q99"):
        if key not in stats:
            raise ValueError(f"action norm stats need {key!r} (got keys {sorted(stats)})")
        out[key] = _vector(stats[key], key)
    out["mask"] = np.asarray(stats.get("mask", [True] * OPENVLA_ACTION_DIM), dtype=bool)
    if out["mask"].shape != (OPENVLA_ACTION_DIM,):
        raise ValueError(f"action norm stats 'mask' must have {OPENVLA_ACTION_DIM} entries")
    for key in ("min", "max"):
        if key in stats:
            out[key] = _vector(stats[key], key)
    return out


def _vector(values, name: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != (OPENVLA_ACTION_DIM,):
        raise ValueError(
            f"action norm stats {name!r} must have {OPENVLA_ACTION_DIM} entries, got shape {arr.shape}"
        )
    return arr


def _check_action(action_id: int) -> None:
    if int(action_id) not in MODEL_ACTION_IDS:
        raise ValueError(
            f"action id {action_id} is not a model action (0..{NUM_ACTIONS - 1}); "
            "map take-off/landing (-1/-2) first"
        )

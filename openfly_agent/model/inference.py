"""Batched closed-loop inference with per-episode memory (`OpenFlyAgent.select_action` / `reset`).

Every call advances each listed episode by one step in one batched prefill: encode the current frames,
build `[BOS] [memory] [current] [prompt]` per episode (left padded), read the action at the last position
(`discrete`) or decode 8 bin tokens greedily with the KV cache (`openvla_bins`), predict the landmark box,
then append the frame's features, box and action to the episode and update its FIFO memory when a keyframe
set completes. Encoded frame features are computed once; the prompt is tokenised once per episode.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch

from openfly_agent.constants import EPISODE_ID, OBS_INSTRUCTION, OBS_RGB

from .config import HEAD_DISCRETE, MODE_OPENVLA_COMPAT
from .memory import MemoryBank
from .sequence import left_pad, position_ids_from_mask

if TYPE_CHECKING:
    from .agent import OpenFlyAgent


@dataclass
class EpisodeState:
    """What the agent remembers about one running episode."""

    instruction: str
    prompt_ids: list[int]  # [BOS] prompt (+ suffix token), tokenised once
    memory: MemoryBank
    actions: list[int] = field(default_factory=list)  # action chosen at each past frame
    boxes: list[tuple[float, float, float, float] | None] = field(default_factory=list)  # None = invisible
    frame_features: dict[int, torch.Tensor] = field(default_factory=dict)  # recent frames: (P, D_v)
    history_tokens: dict[int, torch.Tensor] = field(default_factory=dict)  # compat: frame -> (D,)

    @property
    def step(self) -> int:
        """Index of the next frame."""
        return len(self.actions)

    @property
    def box_areas(self) -> list[float | None]:
        """Predicted box area of each past frame (fraction of the image), None where invisible."""
        return [None if box is None else box[2] * box[3] for box in self.boxes]


@dataclass
class StepResult:
    """One episode's outcome of `predict_step`."""

    action: int
    action_logits: torch.Tensor  # discrete: (10,) logits of the action ids; bins: (8,) generated token ids
    box: tuple[float, float, float, float]  # predicted landmark box (cx, cy, w, h)
    box_visible: bool


def compat_history_indices(step: int, count: int) -> list[int]:
    """Frames shown as history by the released model at `step`: t-count .. t-1 clipped at 0 (eval pads
    by repeating the first frame: [f0, f0, f0], [f0, f0, f1], then [t-2, t-1, t])."""
    return [max(0, step - count + i) for i in range(count)]


def reset_episodes(agent: OpenFlyAgent, episode_ids: Sequence[str] | None = None) -> None:
    """Forget the listed episodes (all when None)."""
    if episode_ids is None:
        agent.episodes.clear()
        return
    for episode_id in episode_ids:
        agent.episodes.pop(episode_id, None)


@torch.no_grad()
def predict_step(agent: OpenFlyAgent, observations: list[dict[str, Any]]) -> list[StepResult]:
    """Advance every observed episode by one step (see module docstring); returns one result each."""
    if not observations:
        return []
    states = [_episode_state(agent, obs) for obs in _checked(observations)]
    device = agent.projector.fc1.weight.device
    pixels = torch.stack([agent.image_transform(obs[OBS_RGB]) for obs in observations]).to(device)
    patches, dino_cls = agent.vision_backbone.forward_with_cls(pixels)  # (B, P, D_v), (B, D_dino)
    current = agent.projector(patches)  # (B, P, D)
    compat = agent.model_cfg.mode == MODE_OPENVLA_COMPAT
    own_history = agent.history_tokens(patches, dino_cls) if compat else None  # (B, D)

    sequences = []
    for row, state in enumerate(states):
        if compat:
            memory = _compat_history(agent, state, own_history[row])
        else:
            memory = torch.cat([current[row, :0], *state.memory.tokens()], dim=0)  # (M, D), oldest first
        prompt = agent.embed_text(torch.tensor(state.prompt_ids, device=device))  # (L, D)
        sequences.append(torch.cat([prompt[:1], memory.to(current.dtype), current[row], prompt[1:]], dim=0))
    embeds, mask = left_pad(sequences)  # (B, L, D), (B, L)
    output = agent.run_llm(embeds, mask, use_cache=agent.action_tokenizer.head != HEAD_DISCRETE)
    hidden = output.last_hidden_state  # (B, L, D)
    actions, details = _decode_actions(agent, hidden, mask, output.past_key_values)
    boxes, visible = _predict_boxes(agent, hidden, mask)

    results = []
    for row, state in enumerate(states):
        box = tuple(float(v) for v in boxes[row])
        results.append(StepResult(actions[row], details[row].cpu(), box, bool(visible[row])))
        state.actions.append(actions[row])
        state.boxes.append(box if visible[row] else None)
        if compat:
            state.history_tokens[state.step - 1] = own_history[row]
            keep = {0, *range(state.step - agent.model_cfg.memory.capacity, state.step)}
            state.history_tokens = {i: t for i, t in state.history_tokens.items() if i in keep}
        else:
            state.frame_features[state.step - 1] = patches[row]
    if not compat:
        _update_memories(agent, states)
    return results


def _checked(observations: list[dict[str, Any]]) -> list[dict[str, Any]]:
    ids = []
    for index, obs in enumerate(observations):
        missing = {EPISODE_ID, OBS_INSTRUCTION, OBS_RGB} - set(obs)
        if missing:
            raise ValueError(f"observation {index} lacks {sorted(missing)} (episode_id, instruction, rgb)")
        ids.append(obs[EPISODE_ID])
    if len(set(ids)) != len(ids):
        raise ValueError(f"an episode appears twice in one select_action call: {ids}")
    return observations


def _episode_state(agent: OpenFlyAgent, obs: dict[str, Any]) -> EpisodeState:
    episode_id, instruction = obs[EPISODE_ID], obs[OBS_INSTRUCTION]
    state = agent.episodes.get(episode_id)
    if state is not None:
        if state.instruction != instruction:
            raise ValueError(f"episode {episode_id!r} changed its instruction: reset([{episode_id!r}]) first")
        return state
    if agent.tokenizer is None:
        raise ValueError("select_action needs a tokenizer: pass one to from_model_config / from_pretrained")
    ids = list(agent.tokenizer(agent.build_prompt(instruction)).input_ids)
    bos = agent.model_cfg.llm.bos_token_id
    if not ids or ids[0] != bos:
        raise ValueError(f"the tokenizer must add BOS ({bos}) at the start; got ids {ids[:5]}...")
    suffix = agent.model_cfg.prompt.suffix_token_id
    if suffix is not None and ids[-1] != suffix:
        ids.append(suffix)  # OpenVLA's predict_action appends '▁' (29871)
    state = EpisodeState(instruction, ids, MemoryBank(agent.model_cfg.memory.capacity))
    agent.episodes[episode_id] = state
    return state


def _compat_history(agent: OpenFlyAgent, state: EpisodeState, own: torch.Tensor) -> torch.Tensor:
    """(K, D) history tokens of the released model's 3-image input."""
    if state.step == 0:
        tokens = [own] * agent.model_cfg.memory.capacity
    else:
        indices = compat_history_indices(state.step, agent.model_cfg.memory.capacity)
        tokens = [state.history_tokens[i] for i in indices]
    return torch.stack(tokens) if tokens else own.new_zeros(0, own.shape[-1])


def _decode_actions(agent: OpenFlyAgent, hidden, mask, cache) -> tuple[list[int], list[torch.Tensor]]:
    tokenizer = agent.action_tokenizer
    last = agent.lm_logits(hidden[:, -1])  # (B, V)
    if tokenizer.head == HEAD_DISCRETE:
        ids = torch.tensor(tokenizer.discrete_token_ids, device=last.device)
        logits = last[:, ids]  # (B, 10)
        return [int(a) for a in logits.argmax(dim=-1)], list(logits)
    tokens = greedy_decode(agent, last, mask, cache, tokenizer.num_action_tokens)  # (B, 8)
    return [tokenizer.token_ids_to_action(row.tolist()) for row in tokens], list(tokens)


def greedy_decode(agent: OpenFlyAgent, first_logits, mask, cache, steps: int) -> torch.Tensor:
    """Greedy decoding of `steps` tokens reusing the prefill's KV cache (as predict_action, any token).

    Args:
        agent: the agent.
        first_logits: (B, V) logits at the last prefill position.
        mask: (B, L) prefill attention mask.
        cache: the prefill's `past_key_values`.
        steps: tokens to generate.

    Returns:
        (B, steps) token ids.
    """
    token = first_logits.argmax(dim=-1)  # (B,)
    generated = [token]
    positions = position_ids_from_mask(mask)[:, -1:]  # (B, 1)
    for _ in range(steps - 1):
        mask = torch.cat([mask, mask.new_ones(mask.shape[0], 1)], dim=1)
        positions = positions + 1
        out = agent.run_llm(
            agent.embed_text(token[:, None]),
            mask,
            position_ids=positions,
            past_key_values=cache,
            use_cache=True,
        )
        cache = out.past_key_values
        token = agent.lm_logits(out.last_hidden_state[:, -1]).argmax(dim=-1)
        generated.append(token)
    return torch.stack(generated, dim=1)


def _predict_boxes(agent: OpenFlyAgent, hidden, mask) -> tuple[torch.Tensor, list[bool]]:
    batch = hidden.shape[0]
    if agent.grounding_head is None:
        return torch.zeros(batch, 4), [False] * batch
    boxes, visibility = agent.grounding_head(hidden, mask.bool())  # (B, 4), (B,)
    if agent.model_cfg.grounding.visibility_weight == 0:
        return boxes.float().cpu(), [True] * batch  # no visibility training: every box counts
    return boxes.float().cpu(), [bool(v) for v in visibility > 0]


def _update_memories(agent: OpenFlyAgent, states: list[EpisodeState]) -> None:
    """Push newly completed keyframe sets (same selector as the dataset, predicted boxes) into the FIFOs."""
    pending = []  # (state, frames)
    for state in states:
        for frames in agent.keyframe_selector.select(state.actions, state.box_areas, state.step):
            if tuple(frames) not in state.memory:
                pending.append((state, frames))
        window = agent.keyframe_selector.set_size
        for index in [i for i in state.frame_features if i < state.step - window]:
            del state.frame_features[index]
    if not pending:
        return
    size = max(len(frames) for _, frames in pending)
    first = next(iter(pending[0][0].frame_features.values()))
    features = first.new_zeros(len(pending), size, *first.shape)  # (N, S, P, D_v)
    frame_mask = torch.zeros(len(pending), size, dtype=torch.bool, device=first.device)
    boxes = torch.zeros(len(pending), size, 4, device=first.device)
    for row, (state, frames) in enumerate(pending):
        for col, frame in enumerate(frames):
            features[row, col] = state.frame_features[frame]
            boxes[row, col] = torch.tensor(state.boxes[frame], device=first.device)
        frame_mask[row, : len(frames)] = True
    tokens = agent.memory_set_tokens(features, frame_mask, boxes, frame_mask)  # (N, m, D)
    for row, (state, frames) in enumerate(pending):
        state.memory.push(tuple(frames), tokens[row])

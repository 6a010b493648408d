"""`AgentSession`: the agent in closed loop, as lerobot's policies: `select_action(observations)` /
`predict_step` / `reset(episode_ids)`, with every running episode's state (model/episode.py) in `self.episodes`.

The session holds what episodes need between steps; the agent (model/agent.py) stays a stateless model: its
processor prepares the inputs, its network (model/network.py) encodes and decodes.
"""

from __future__ import annotations

from typing import Any, Protocol

import torch

from openfly_agent.constants import (
    EPISODE_ID,
    MEMORY_PROBE_EMPTY,
    MEMORY_PROBE_NONE,
    MEMORY_PROBES,
    OBS_INSTRUCTION,
    OBS_RGB,
)
from openfly_agent.model.config import HEAD_DISCRETE
from openfly_agent.model.episode import Box, EpisodeState, StepResult, check_observations
from openfly_agent.model.language.action_tokenizer import ActionTokenizer
from openfly_agent.model.layout import SequenceLayout
from openfly_agent.model.network import OpenFlyNetwork, given_boxes
from openfly_agent.model.processor import OpenFlyProcessor


class SessionAgent(Protocol):
    """What a session reads of its agent (`OpenFlyAgent`, model/agent.py), each step anew: `set_action_decoding`
    may rebuild the processor and the action tokenizer."""

    network: OpenFlyNetwork
    processor: OpenFlyProcessor | None
    action_tokenizer: ActionTokenizer


class AgentSession:
    """Running episodes of one agent, stepped together in one batch, each with its own memory.

    Args:
        agent: the `OpenFlyAgent` that acts (its processor is needed once an episode starts).
        memory_probe: `none` (the model as trained) or `empty`: every step reads no memory token, while each
            episode's memory still records its frames (`constants.MEMORY_PROBES`; an evaluation diagnostic).
        temperature: 0 picks the most likely action (greedy, the default); > 0 samples it from
            softmax(action logits / temperature) with `generator` (the RL stage's rollouts; `discrete` head only).
        generator: the random stream of the samples (None: torch's global one).
    """

    def __init__(
        self,
        agent: SessionAgent,
        memory_probe: str = MEMORY_PROBE_NONE,
        temperature: float = 0.0,
        generator: torch.Generator | None = None,
    ) -> None:
        if memory_probe not in MEMORY_PROBES:
            raise ValueError(f"memory_probe={memory_probe!r}: choose one of {MEMORY_PROBES}")
        if temperature < 0:
            raise ValueError(f"temperature must be >= 0, got {temperature}")
        if temperature > 0 and agent.action_tokenizer.head != HEAD_DISCRETE:
            raise ValueError(f"sampling (temperature {temperature}) needs the {HEAD_DISCRETE} action head")
        self.agent = agent
        self.memory_probe = memory_probe
        self.temperature, self.generator = float(temperature), generator
        self.episodes: dict[str, EpisodeState] = {}

    def select_action(self, observations: list[dict[str, Any]]) -> list[int]:
        """One action per observation, all episodes in one batch, each with its own memory.

        Args:
            observations: dicts with `episode_id`, `instruction`, `rgb` ((H, W, 3) uint8) and `pose`.

        Returns:
            Action ids 0..9, in the order of `observations`.
        """
        return [result.action for result in self.predict_step(observations)]

    @torch.no_grad()
    def predict_step(
        self, observations: list[dict[str, Any]], true_boxes: list[Box | None] | None = None
    ) -> list[StepResult]:
        """`select_action` with details: action logits (or bin tokens), the predicted landmark box and the
        keyframe sets in memory.

        `true_boxes` (one (cx, cy, w, h) or None = not visible per observation; evaluation only) replaces the
        grounding head's prediction in the box token and the keyframe memory: the agent with perfect
        grounding, which splits its gap to the expert into perception and policy.

        One step of every observed episode, as training's forward: `encode` the current frames and each
        episode's memory, lay them out with the prompts (`SequenceLayout.for_inference`: the training layout
        left padded, without BOX and the action), run the network's backbone with a KV cache where later steps need one,
        read the `heads`: the landmark box, then (with the box token, one cached step later) the action at the
        last position (`discrete`) or 8 bin tokens decoded greedily (`openvla_bins`); then record the step in
        the episode's state and let the memory encoding remember it. Each frame is encoded once; the prompt once
        per episode.
        """
        if not observations:
            return []
        check_observations(observations)
        if true_boxes is not None and len(true_boxes) != len(observations):
            raise ValueError(f"{len(true_boxes)} true boxes for {len(observations)} observations")
        network, processor = self.agent.network, self.agent.processor
        tokenizer = self.agent.action_tokenizer
        states = [self._episode_state(obs[EPISODE_ID], obs[OBS_INSTRUCTION]) for obs in observations]
        device = network.projector.fc1.weight.device
        pixels = torch.stack([processor.image(obs[OBS_RGB]) for obs in observations]).to(device)
        frames, memories = network.encode_step(pixels, states)  # (M_i, D) memory tokens per episode
        if self.memory_probe == MEMORY_PROBE_EMPTY:
            memories = [memory[:0] for memory in memories]  # (0, D) per episode
        prompts = [network.embed_text(torch.tensor(state.prompt_ids, device=device)) for state in states]
        layout = SequenceLayout.for_inference(prompts, memories, frames.current)  # [pad] .. [prompt]
        # the cache is filled by the prefill and read by the steps after it (BOX, decoded bin tokens)
        box_token = network.box_token_embed is not None
        cache = network.new_cache() if tokenizer.head != HEAD_DISCRETE or box_token else None
        hidden = network(layout, cache)  # (B, L_max, D)
        # the head's prediction is not computed when the true boxes replace it
        colours = network.cell_colours(pixels) if true_boxes is None else None  # (B, P, C + 1) or None
        logits, grounding = network.heads(hidden, layout, not box_token, true_boxes is None, colours)
        if true_boxes is None:
            boxes, visible = network.predicted_boxes(grounding, len(states))
        else:
            boxes, visible = given_boxes(true_boxes, device)
        if box_token:  # [.. prompt] [BOX]: one cached step, the action is read there
            layout = layout.then(network.box_token(boxes.to(device), torch.tensor(visible, device=device)))
            logits, _ = network.heads(network(layout, cache), layout, boxes=False)  # (B, V)
        decoded = network.decode_actions(logits, layout, cache, tokenizer)  # (B, 10) or (B, 8)
        if tokenizer.head == HEAD_DISCRETE and self.temperature > 0:
            probs = torch.softmax(decoded.float() / self.temperature, dim=-1).cpu()  # (B, 10)
            actions = [int(a) for a in torch.multinomial(probs, 1, generator=self.generator)[:, 0]]
        elif tokenizer.head == HEAD_DISCRETE:
            actions = [int(a) for a in decoded.argmax(dim=-1)]
        else:
            actions = [processor.decode_action(row.tolist()) for row in decoded]
        boxes = boxes.float().cpu()
        for row, state in enumerate(states):
            state.record(actions[row], tuple(float(v) for v in boxes[row]) if visible[row] else None)
        network.write_memory(states, frames)
        return [
            StepResult(
                actions[row],
                decoded[row].cpu(),
                tuple(float(v) for v in boxes[row]),
                bool(visible[row]),
                state.memory.sets(),
            )
            for row, state in enumerate(states)
        ]

    def reset(self, episode_ids: list[str] | None = None) -> None:
        """Forget the listed episodes (every episode when None)."""
        if episode_ids is None:
            self.episodes.clear()
        for episode_id in episode_ids or []:
            self.episodes.pop(episode_id, None)

    def _episode_state(self, episode_id: str, instruction: str) -> EpisodeState:
        """The state of a running episode, or a new one with its prompt tokenised by the processor."""
        state = self.episodes.get(episode_id)
        if state is not None:
            if state.instruction != instruction:
                raise ValueError(
                    f"episode {episode_id!r} changed its instruction: reset([{episode_id!r}]) first"
                )
            return state
        processor = self.agent.processor
        if processor is None:
            raise ValueError(
                "select_action needs a tokenizer: pass one to from_model_config / from_pretrained"
            )
        prompt_ids, _ = processor.encode(processor.navigation_prompt(instruction))
        state = EpisodeState(instruction, prompt_ids, self.agent.network.memory.new_episode())
        self.episodes[episode_id] = state
        return state

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
from openfly_agent.model.grounding.box_token import given_boxes
from openfly_agent.model.language.action_tokenizer import ActionTokenizer
from openfly_agent.model.language.sequence import left_pad
from openfly_agent.model.network import OpenFlyNetwork
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

        One step of every observed episode in one left-padded prefill: encode the current frames, build
        `[BOS] [memory] [current] [prompt]` per episode (the training layout without the action tokens), read
        the action at the last position (`discrete`) or decode 8 bin tokens greedily with the KV cache
        (`openvla_bins`), predict the landmark box, then record the step in the episode's state and let the
        memory encoding remember it. Each frame is encoded once; the prompt once per episode.
        """
        if not observations:
            return []
        check_observations(observations)
        if true_boxes is not None and len(true_boxes) != len(observations):
            raise ValueError(f"{len(true_boxes)} true boxes for {len(observations)} observations")
        network, processor = self.agent.network, self.agent.processor
        states = [self._episode_state(obs[EPISODE_ID], obs[OBS_INSTRUCTION]) for obs in observations]
        device = network.projector.fc1.weight.device
        pixels = torch.stack([processor.image(obs[OBS_RGB]) for obs in observations]).to(device)
        frames = network.encode_step(pixels)
        memories = network.read_memory(states, frames)  # (M_i, D) per episode
        if self.memory_probe == MEMORY_PROBE_EMPTY:
            memories = [memory[:0] for memory in memories]  # (0, D) per episode
        sequences = []
        for row, state in enumerate(states):
            prompt = network.embed_text(torch.tensor(state.prompt_ids, device=device))  # (L, D)
            sequences.append(
                torch.cat(
                    [prompt[:1], memories[row].to(frames.current.dtype), frames.current[row], prompt[1:]]
                )
            )
        embeds, mask = left_pad(sequences)  # (B, L_max, D), (B, L_max)
        # the cache is filled by the prefill and read by the decoding after it
        needs_cache = self.agent.action_tokenizer.head != HEAD_DISCRETE or network.box_token_embed is not None
        cache = network.new_cache() if needs_cache else None
        if cache is None:
            output = network.run_llm(embeds, mask, use_cache=False)
        else:
            output = network.run_cached(embeds, mask, cache)
        hidden = output.last_hidden_state  # (B, L_max, D)
        if true_boxes is None:
            padding = mask.shape[1] - mask.sum(dim=1)  # (B,) left padding of each row
            memory_sizes = torch.tensor([memory.shape[0] for memory in memories], device=mask.device)
            first_image = padding + 1 + memory_sizes  # after [pad] [BOS] [memory]
            boxes, visible = network.predict_boxes(hidden, mask, first_image, frames.current)
        else:  # the head's prediction would be discarded: not computed
            boxes, visible = given_boxes(true_boxes, device)
        if (
            network.box_token_embed is not None
        ):  # [.. prompt] [BOX]: one cached step, the action is read there
            token = network.box_token_embed(boxes.to(device), torch.tensor(visible, device=device))  # (B, D)
            hidden, mask = network.decode_one(token, mask, cache)
        decoded = network.decode_actions(
            hidden, mask, cache, self.agent.action_tokenizer
        )  # (B, 10) or (B, 8)
        if self.agent.action_tokenizer.head == HEAD_DISCRETE and self.temperature > 0:
            probs = torch.softmax(decoded.float() / self.temperature, dim=-1).cpu()  # (B, 10)
            actions = [int(a) for a in torch.multinomial(probs, 1, generator=self.generator)[:, 0]]
        elif self.agent.action_tokenizer.head == HEAD_DISCRETE:
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

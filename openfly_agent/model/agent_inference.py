"""Closed-loop inference of the agent, as lerobot's policies: `select_action(observations)` / `predict_step` /
`reset(episode_ids)`, every running episode's state (model/episode.py) in `self.episodes`.

`ClosedLoopInference` is a mixin of `OpenFlyAgent` (model/agent.py): it uses the agent's `processor`,
`vision_backbone`, `projector`, `run_llm`, `lm_logits`, `ground`, `box_token_embed`, `action_tokenizer`,
`keyframe_selector`, `model_cfg` and the memory encoding of model/memory/encoding.py.
"""

from __future__ import annotations

from typing import Any

import torch

from openfly_agent.constants import EPISODE_ID, OBS_INSTRUCTION, OBS_RGB
from openfly_agent.model.config import HEAD_DISCRETE, MODE_OPENVLA_COMPAT
from openfly_agent.model.episode import Box, EpisodeState, StepResult, check_observations
from openfly_agent.model.grounding.box_token import given_boxes
from openfly_agent.model.language.decoding import decode_one, greedy_decode, new_cache, run_cached
from openfly_agent.model.language.sequence import left_pad
from openfly_agent.model.memory.bank import MemoryBank


class ClosedLoopInference:
    """One batched step of every observed episode, each with its own keyframe memory."""

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
        """`select_action` with details: action logits (or bin tokens) and the predicted landmark box.

        `true_boxes` (one (cx, cy, w, h) or None = not visible per observation; evaluation only) replaces the
        grounding head's prediction in the box token and the keyframe memory: the agent with perfect
        grounding, which splits its gap to the expert into perception and policy.

        One step of every observed episode in one left-padded prefill: encode the current frames, build
        `[BOS] [memory] [current] [prompt]` per episode (the training layout without the action tokens), read
        the action at the last position (`discrete`) or decode 8 bin tokens greedily with the KV cache
        (`openvla_bins`), predict the landmark box, then record the step in the episode's state and push
        keyframe sets that completed into its memory. Each frame is encoded once; the prompt once per episode.
        """
        if not observations:
            return []
        check_observations(observations)
        states = [self._episode_state(obs[EPISODE_ID], obs[OBS_INSTRUCTION]) for obs in observations]
        device = self.projector.fc1.weight.device
        pixels = torch.stack([self.processor.image(obs[OBS_RGB]) for obs in observations]).to(device)
        patches, dino_cls = self.vision_backbone.forward_with_cls(pixels)  # (B, P, D_v), (B, D_dino) or None
        current = self.projector(patches)  # (B, P, D)
        compat = self.model_cfg.mode == MODE_OPENVLA_COMPAT
        own_history = self.history_tokens(patches, dino_cls) if compat else None  # (B, D)

        sequences, memory_sizes = [], []
        for row, state in enumerate(states):
            if compat:
                memory = state.compat_history(own_history[row], self.model_cfg.memory.capacity)  # (K, D)
            else:
                memory = torch.cat([current[row, :0], *state.memory.tokens()], dim=0)  # (M, D), oldest first
            prompt = self.embed_text(torch.tensor(state.prompt_ids, device=device))  # (L, D)
            sequences.append(
                torch.cat([prompt[:1], memory.to(current.dtype), current[row], prompt[1:]], dim=0)
            )
            memory_sizes.append(memory.shape[0])
        embeds, mask = left_pad(sequences)  # (B, L_max, D), (B, L_max)
        needs_cache = self.action_tokenizer.head != HEAD_DISCRETE or self.box_token_embed is not None
        # the cache is filled by the prefill and read by the decoding after it
        cache = new_cache(self) if needs_cache else None
        if cache is None:
            output = self.run_llm(embeds, mask, use_cache=False)
        else:
            output = run_cached(self, embeds, mask, cache)
        hidden = output.last_hidden_state  # (B, L_max, D)
        padding = mask.shape[1] - mask.sum(dim=1)  # (B,) left padding of each row
        first_image = (
            padding + 1 + torch.tensor(memory_sizes, device=mask.device)
        )  # after [pad] [BOS] [memory]
        if true_boxes is None:
            boxes, visible = self._predict_boxes(hidden, mask, first_image, current)
        elif len(true_boxes) != len(observations):
            raise ValueError(f"{len(true_boxes)} true boxes for {len(observations)} observations")
        else:  # the head's prediction would be discarded: not computed
            boxes, visible = given_boxes(true_boxes, device)
        if self.box_token_embed is not None:  # [.. prompt] [BOX]: one cached step, the action is read there
            token = self.box_token_embed(boxes.to(device), torch.tensor(visible, device=device))  # (B, D)
            hidden, mask = decode_one(self, token, mask, cache)
        actions, details = self._decode_actions(hidden, mask, cache)
        boxes = boxes.float().cpu()

        results = []
        for row, state in enumerate(states):
            box = tuple(float(v) for v in boxes[row])
            results.append(StepResult(actions[row], details[row].cpu(), box, bool(visible[row])))
            frame = state.record(actions[row], box if visible[row] else None)
            if compat:
                state.keep_history_token(frame, own_history[row], self.model_cfg.memory.capacity)
            else:
                state.frame_features[frame] = patches[row]
        if not compat:
            self._update_memories(states)
        return results

    def reset(self, episode_ids: list[str] | None = None) -> None:
        """Forget the memory of the listed episodes (every episode when None)."""
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
        if self.processor is None:
            raise ValueError(
                "select_action needs a tokenizer: pass one to from_model_config / from_pretrained"
            )
        prompt_ids, _ = self.processor.encode(self.processor.navigation_prompt(instruction))
        state = EpisodeState(instruction, prompt_ids, MemoryBank(self.model_cfg.memory.capacity))
        self.episodes[episode_id] = state
        return state

    def _decode_actions(self, hidden, mask, cache) -> tuple[list[int], list[torch.Tensor]]:
        """Discrete: argmax over the 10 action ids at the last position. Bins: 8 greedy tokens, decoded."""
        last = self.lm_logits(hidden[:, -1])  # (B, V)
        if self.action_tokenizer.head == HEAD_DISCRETE:
            ids = torch.tensor(self.action_tokenizer.discrete_token_ids, device=last.device)
            logits = last[:, ids]  # (B, 10)
            return [int(a) for a in logits.argmax(dim=-1)], list(logits)
        tokens = greedy_decode(self, last, mask, cache, self.action_tokenizer.num_action_tokens)  # (B, 8)
        return [self.processor.decode_action(row.tolist()) for row in tokens], list(tokens)

    def _predict_boxes(self, hidden, mask, first_image, current) -> tuple[torch.Tensor, list[bool]]:
        """(B, 4) predicted boxes and whether each counts as visible (prefill of left-padded rows; `current`: the
        (B, P, D) current frames' tokens as they entered the LLM)."""
        batch = hidden.shape[0]
        if self.grounding_head is None:
            return hidden.new_zeros(batch, 4), [False] * batch
        output = self.ground(hidden, mask.bool(), first_image, current)
        if self.model_cfg.grounding.visibility_weight == 0:
            return output.boxes.float(), [True] * batch  # no visibility training: every box counts
        return output.boxes.float(), [bool(v) for v in output.visibility > 0]

    def _update_memories(self, states: list[EpisodeState]) -> None:
        """Push newly completed keyframe sets (same selector as the dataset, predicted boxes) into the FIFOs."""
        pending = []  # (state, frames)
        for state in states:
            for frames in self.keyframe_selector.select(state.actions, state.box_areas, state.step):
                if tuple(frames) not in state.memory:
                    pending.append((state, frames))
            state.forget_features_before(state.step - self.keyframe_selector.set_size)
        if not pending:
            return
        size = max(len(frames) for _, frames in pending)
        first = next(iter(pending[0][0].frame_features.values()))
        features = first.new_zeros(len(pending), size, *first.shape)  # (N, S, P, D_v)
        frame_mask = torch.zeros(len(pending), size, dtype=torch.bool, device=first.device)  # (N, S)
        boxes = torch.zeros(len(pending), size, 4, device=first.device)  # (N, S, 4)
        for row, (state, frames) in enumerate(pending):
            for col, frame in enumerate(frames):
                features[row, col] = state.frame_features[frame]
                boxes[row, col] = torch.tensor(state.boxes[frame], device=first.device)
            frame_mask[row, : len(frames)] = True
        tokens = self.memory_set_tokens(features, frame_mask, boxes, frame_mask)  # (N, m, D)
        for row, (state, frames) in enumerate(pending):
            state.memory.push(tuple(frames), tokens[row])

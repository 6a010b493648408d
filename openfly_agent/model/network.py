"""`OpenFlyNetwork`: the agent's modules and its two halves, as timm's `forward_features` / `forward_head`.

`encode` turns frames and memory into visual tokens (training batch), `encode_step` the frames of one
closed-loop step and `read_memory` / `write_memory` each running episode's memory; the LLM runs between; `predict_boxes` / `decode_actions` turn hidden states into the landmark
box and the action (logits, or bin tokens decoded greedily with the KV cache: `new_cache`, `run_cached`,
`decode_one`, `greedy_decode`). The memory encoding (keyframe sets or the OpenVLA-compatible history) is chosen
once from the config (`self.memory`, model/memory/encoding.py). Loss, processor and save / load belong to the
`OpenFlyAgent` around it (model/agent.py); the running episodes to `AgentSession` (model/session.py).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from openfly_agent.constants import FRAME_INDEX, MEMORY_PIXEL_VALUES, PIXEL_VALUES
from openfly_agent.model.config import HEAD_DISCRETE, ModelConfig
from openfly_agent.model.episode import EpisodeState
from openfly_agent.model.factory import make_memory_encoding
from openfly_agent.model.grounding.box_token import BoxTokenEmbedding, last_true_index
from openfly_agent.model.grounding.head import GroundingOutput, make_grounding_head
from openfly_agent.model.language.action_tokenizer import ActionTokenizer
from openfly_agent.model.language.llm import build_language_model, cache_keyword, unwrap_causal_lm
from openfly_agent.model.language.sequence import position_ids_from_mask
from openfly_agent.model.memory.encoding import StepFrames
from openfly_agent.model.memory.keyframes import KeyframeSelector
from openfly_agent.model.vision.backbone import build_vision_backbone, encode_frames
from openfly_agent.model.vision.projector import FusedMLPProjector


class OpenFlyNetwork(nn.Module):
    """Vision backbone, projector, LLM, grounding head and box-token embedding, under OpenVLA's module names.

    Args:
        cfg: the resolved model sections (`llm.vocab_size` set); the network reads its structural sections
            (vision, projector, llm, grounding, memory, merging, keyframes), never the action decoding.
    """

    def __init__(self, cfg: ModelConfig) -> None:
        super().__init__()
        self.cfg = cfg
        llm_dim = cfg.llm.hidden_size
        self.vision_backbone = build_vision_backbone(cfg.vision)
        self.projector = FusedMLPProjector(cfg.vision.feature_dim, llm_dim, cfg.projector.hidden_ratio)
        self.language_model = build_language_model(cfg.llm, cfg.llm.vocab_size)
        # absent heads are registered as None: the agent, which shares these modules, reads them by name
        self.register_module(
            "grounding_head", make_grounding_head(llm_dim, cfg.grounding, cfg.vision.grid_side)
        )
        self.register_module("box_token_embed", BoxTokenEmbedding(llm_dim) if cfg.uses_box_token else None)
        self.keyframe_selector = KeyframeSelector.from_config(cfg.keyframes, cfg.memory.capacity)
        self.memory = make_memory_encoding(cfg, self.keyframe_selector)

    @property
    def llm_dim(self) -> int:
        """LLM hidden size."""
        return self.cfg.llm.hidden_size

    # --- encode: frames + memory -> visual tokens -------------------------------------------------
    def embed_text(self, input_ids: torch.Tensor) -> torch.Tensor:
        """(B, L) ids -> (B, L, D) input embeddings."""
        return unwrap_causal_lm(self.language_model).get_input_embeddings()(input_ids)

    def encode(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """Visual tokens of a training batch: memory (oldest first) then the current frame.

        A grounding batch may hold fewer frames than sequences: `frame_index` (B,) says which frame of
        `pixel_values` (F, 3, H, W) each sequence reads (each frame is encoded once).

        Returns:
            (B, M + P, D) tokens and their (B, M + P) bool mask (False on missing memory sets).
        """
        current = self.projector(
            encode_frames(self.vision_backbone, batch[PIXEL_VALUES], batch.get(FRAME_INDEX))
        )  # (B, P, D)
        memory, memory_mask = self._batch_memory(batch)  # (B, M, D), (B, M)
        if memory.shape[0] != current.shape[0]:  # a grounding batch has no memory: one empty row per sequence
            memory = current.new_zeros(current.shape[0], 0, current.shape[-1])  # (B, 0, D)
            memory_mask = torch.zeros(current.shape[0], 0, dtype=torch.bool, device=current.device)
        visual = torch.cat([memory.to(current.dtype), current], dim=1)  # (B, M + P, D)
        return visual, torch.cat([memory_mask, memory_mask.new_ones(current.shape[:2])], dim=1)

    def _batch_memory(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, M, D) memory tokens of a training batch and their (B, M) bool mask; M = 0 without memory."""
        b = batch[PIXEL_VALUES].shape[0]
        device = batch[PIXEL_VALUES].device
        capacity = self.cfg.memory.capacity
        if capacity == 0 or MEMORY_PIXEL_VALUES not in batch:
            empty = torch.zeros(b, 0, self.llm_dim, device=device, dtype=self.projector.fc1.weight.dtype)
            return empty, torch.zeros(b, 0, dtype=torch.bool, device=device)
        sets = batch[MEMORY_PIXEL_VALUES].shape[1]  # (B, K, S, 3, H, W)
        if sets > capacity:
            raise ValueError(f"batch holds {sets} memory sets but memory.capacity is {capacity}")
        return self.memory.batch_tokens(self.vision_backbone, self.projector, batch)

    def encode_step(self, pixels: torch.Tensor) -> StepFrames:
        """The current frames of one closed-loop step: (B, 3, H, W) uint8 -> backbone features, DINO CLS
        (the ViTs; None for the CNN) and projected tokens."""
        patches, dino_cls = self.vision_backbone.forward_with_cls(pixels)  # (B, P, D_v), (B, D_dino) or None
        return StepFrames(patches, dino_cls, self.projector(patches))

    def read_memory(self, episodes: list[EpisodeState], frames: StepFrames) -> list[torch.Tensor]:
        """Each running episode's (M_i, D) memory tokens at this step, oldest first."""
        return self.memory.read(self.vision_backbone, self.projector, episodes, frames)

    def write_memory(self, episodes: list[EpisodeState], frames: StepFrames) -> None:
        """Remember this step's frames in each episode's memory (after the episode recorded the step)."""
        self.memory.write(self.projector, episodes, frames)

    # --- the LLM ----------------------------------------------------------------------------------
    def run_llm(self, embeds: torch.Tensor, attention_mask: torch.Tensor, **kwargs) -> Any:
        """Decoder stack without the LM head -> transformers output (last_hidden_state, past_key_values)."""
        kwargs.setdefault("position_ids", position_ids_from_mask(attention_mask))
        core = unwrap_causal_lm(self.language_model).model
        return core(inputs_embeds=embeds, attention_mask=attention_mask, **kwargs)

    def lm_logits(self, hidden: torch.Tensor) -> torch.Tensor:
        """LM head on selected hidden states -> float32 logits."""
        return unwrap_causal_lm(self.language_model).lm_head(hidden).float()

    # --- decode: hidden states -> box, action -----------------------------------------------------
    def ground(
        self, hidden: torch.Tensor, readable: torch.Tensor, first_image, current: torch.Tensor | None = None
    ) -> GroundingOutput:
        """The grounding head on a sequence's hidden states.

        Args:
            hidden: (B, L, D) LLM hidden states.
            readable: (B, L) bool, the positions the head may read (image + prompt; no padding, targets or box).
            first_image: (B,) long or int, position of each row's first current-frame token.
            current: (B, P, D) the current frame's visual tokens as they entered the LLM (read with
                `grounding.visual_skip`).
        """
        p = self.cfg.vision.num_patches
        first = torch.as_tensor(first_image, device=hidden.device).reshape(-1, 1)  # (B or 1, 1)
        image_positions = (first + torch.arange(p, device=hidden.device)[None]).expand(hidden.shape[0], p)
        return self.grounding_head(hidden, readable, image_positions, last_true_index(readable), current)

    def predict_boxes(
        self, hidden: torch.Tensor, mask: torch.Tensor, first_image: torch.Tensor, current: torch.Tensor
    ) -> tuple[torch.Tensor, list[bool]]:
        """(B, 4) predicted boxes and whether each counts as visible (prefill of left-padded rows; `current`: the
        (B, P, D) current frames' tokens as they entered the LLM)."""
        batch = hidden.shape[0]
        if self.grounding_head is None:
            return hidden.new_zeros(batch, 4), [False] * batch
        output = self.ground(hidden, mask.bool(), first_image, current)
        if self.cfg.grounding.visibility_weight == 0:
            return output.boxes.float(), [True] * batch  # no visibility training: every box counts
        return output.boxes.float(), [bool(v) for v in output.visibility > 0]

    def decode_actions(
        self, hidden: torch.Tensor, mask: torch.Tensor, cache, action_tokenizer: ActionTokenizer
    ) -> torch.Tensor:
        """Discrete head: (B, 10) logits of the action ids at the last position. Bins head: (B, 8) token ids
        decoded greedily after the prefill (its `cache`, extended in place)."""
        last = self.lm_logits(hidden[:, -1])  # (B, V)
        if action_tokenizer.head == HEAD_DISCRETE:
            ids = torch.tensor(action_tokenizer.discrete_token_ids, device=last.device)
            return last[:, ids]  # (B, 10)
        return self.greedy_decode(last, mask, cache, action_tokenizer.num_action_tokens)  # (B, 8)

    # --- cached decoding --------------------------------------------------------------------------
    # The cache is a transformers `DynamicCache` filled in place by every call, passed under the decoder's own
    # keyword (`cache`; `past_key_values` before transformers renamed it): no deprecated name is used and the
    # output's cache attribute is never read.
    def new_cache(self) -> Any:
        """An empty `DynamicCache` for the LLM."""
        from transformers import DynamicCache

        return DynamicCache(config=unwrap_causal_lm(self.language_model).config)

    def run_cached(self, embeds: torch.Tensor, mask: torch.Tensor, cache, **kwargs) -> Any:
        """`run_llm` over (B, T, D) `embeds` that reads and extends `cache` (in place)."""
        keyword = cache_keyword(type(unwrap_causal_lm(self.language_model).model))
        return self.run_llm(embeds, mask, use_cache=True, **{keyword: cache}, **kwargs)

    def decode_one(self, token: torch.Tensor, mask: torch.Tensor, cache) -> tuple[torch.Tensor, torch.Tensor]:
        """Feed one (B, D) input embedding after the prefill (its `cache`) -> its (B, 1, D) hidden state and the
        (B, L + 1) mask."""
        positions = position_ids_from_mask(mask)[:, -1:] + 1  # (B, 1)
        mask = torch.cat([mask, mask.new_ones(mask.shape[0], 1)], dim=1)
        out = self.run_cached(token[:, None], mask, cache, position_ids=positions)
        return out.last_hidden_state, mask

    def greedy_decode(
        self, first_logits: torch.Tensor, mask: torch.Tensor, cache, steps: int
    ) -> torch.Tensor:
        """Greedy decoding of `steps` tokens reusing the prefill's KV cache (as predict_action, any token).

        Args:
            first_logits: (B, V) logits at the last prefill position.
            mask: (B, L) prefill attention mask.
            cache: the prefill's cache (`new_cache`, filled by `run_cached`).
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
            out = self.run_cached(self.embed_text(token[:, None]), mask, cache, position_ids=positions)
            token = self.lm_logits(out.last_hidden_state[:, -1]).argmax(dim=-1)
            generated.append(token)
        return torch.stack(generated, dim=1)

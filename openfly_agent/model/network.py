"""`OpenFlyNetwork`: the agent's modules behind three entry points, as timm's `forward_features` / `forward_head`.

`encode` turns a training batch's frames and memory into visual tokens (`encode_step`: one closed-loop step's
frames and each running episode's memory); `SequenceLayout` (model/layout.py) places them with the text;
the backbone, `network(layout, cache=None)` (its `forward`), runs the LLM over the layout (right-padded rows in length groups, or a
left-padded prefill and its cached steps); `heads(hidden, layout)` reads the action logits and the grounding
head's output where the layout says. Training (`OpenFlyAgent.forward`, model/agent.py) and inference
(`AgentSession.predict_step`, model/session.py) call the same three. The memory encoding (keyframe sets or the
OpenVLA-compatible history) is chosen once from the config (`self.memory`, model/memory/encoding.py). Loss,
processor and save / load belong to the agent around it; the running episodes to the session.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from openfly_agent.constants import FRAME_INDEX, MEMORY_PIXEL_VALUES, PIXEL_VALUES
from openfly_agent.model.config import HEAD_DISCRETE, ModelConfig
from openfly_agent.model.episode import EpisodeState
from openfly_agent.model.factory import make_memory_encoding
from openfly_agent.model.grounding.head import GroundingOutput, make_grounding_head
from openfly_agent.model.language.action_tokenizer import ActionTokenizer
from openfly_agent.model.language.llm import build_language_model, cache_keyword
from openfly_agent.model.layout import (
    PADDING_RIGHT,
    SequenceLayout,
    last_true_index,
    position_ids_from_mask,
    run_in_length_groups,
)
from openfly_agent.model.memory.encoding import StepFrames
from openfly_agent.model.memory.keyframes import KeyframeSelector
from openfly_agent.model.vision.backbone import build_vision_backbone, encode_frames

# --- the projector: visual features -> LLM input embeddings -------------------------------------------------
# fc1's width as a multiple of the vision width: OpenVLA's 4 x 2176 = 8704 (a setting until issue 46, which no
# config or experiment changed).
PROJECTOR_HIDDEN_RATIO = 4


class FusedMLPProjector(nn.Module):
    """Vision-to-LLM projector, Prismatic's fused GELU MLP under the OpenVLA key names: fc1 (D_v -> 4 D_v) -> GELU
    -> fc2 (-> D_llm) -> GELU -> fc3 (D_llm -> D_llm).

    Args:
        vision_dim: fused vision feature width (2176 for dinosiglip-224px).
        llm_dim: LLM hidden size.
    """

    def __init__(self, vision_dim: int, llm_dim: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(vision_dim, PROJECTOR_HIDDEN_RATIO * vision_dim)
        self.fc2 = nn.Linear(PROJECTOR_HIDDEN_RATIO * vision_dim, llm_dim)
        self.fc3 = nn.Linear(llm_dim, llm_dim)
        self.act = nn.GELU()

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(..., D_v) -> (..., D_llm)."""
        features = features.to(self.fc1.weight.dtype)
        return self.fc3(self.act(self.fc2(self.act(self.fc1(features)))))


# --- the box token: the target's box as one input embedding after the prompt --------------------------------
NUM_BOX_FEATURES = 6  # visible, cx - 0.5, cy - 0.5, sqrt(area), w, h


def box_features(boxes: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """(B, 4) cxcywh in [0, 1] and (B,) bool -> (B, 6) features; all zeros for an invisible target."""
    cx, cy, w, h = boxes.float().unbind(-1)
    features = torch.stack(
        [torch.ones_like(cx), cx - 0.5, cy - 0.5, (w * h).clamp(min=0).sqrt(), w, h], dim=-1
    )
    return features * visible.to(features.dtype)[:, None]


def given_boxes(boxes: list, device=None) -> tuple[torch.Tensor, list[bool]]:
    """A list of (cx, cy, w, h) or None (not visible) -> (B, 4) float boxes (zeros where None), (B,) visibility."""
    rows = [[0.0] * 4 if box is None else [float(v) for v in box] for box in boxes]
    if any(len(row) != 4 for row in rows):
        raise ValueError(f"boxes must be (cx, cy, w, h) or None, got {boxes}")
    return torch.tensor(rows, dtype=torch.float32, device=device), [box is not None for box in boxes]


def jitter_boxes(boxes: torch.Tensor, std: float) -> torch.Tensor:
    """Training noise on (B, 4) cxcywh: the centre moves by N(0, std), width and height scale by exp(N(0, 2 std))."""
    if std <= 0:
        return boxes
    centre = boxes[:, :2] + torch.randn_like(boxes[:, :2]) * std
    size = boxes[:, 2:] * torch.exp(torch.randn_like(boxes[:, 2:]) * 2 * std)
    return torch.cat([centre, size], dim=-1).clamp(0.0, 1.0)


class BoxTokenEmbedding(nn.Module):
    """(B, 6) box features -> (B, D) an input embedding of the LLM (a 2-layer GELU MLP): the BOX token.

    With `action_head.box_token` the step's sequence is `[BOS] [memory] [current] [prompt] [BOX] -> action`: the
    LLM reads the action at the BOX position, whose input embedding encodes where the instruction's target is in
    the frame. At inference BOX carries the grounding head's prediction from the prefill of `[BOS] .. [prompt]`
    (then one cached decode step); in training the ground-truth box, jittered (`jitter_boxes`) so the action learns
    to tolerate a grounding head's errors. The grounding head never reads the BOX position, so both see the same
    prefix. Where BOX goes is the sequence layout's (model/layout.py); this class makes its embedding.
    """

    def __init__(self, llm_dim: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(NUM_BOX_FEATURES, llm_dim)
        self.fc2 = nn.Linear(llm_dim, llm_dim)

    def forward(self, boxes: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
        features = box_features(boxes, visible).to(self.fc1.weight.dtype)
        return self.fc2(nn.functional.gelu(self.fc1(features)))


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
        self.projector = FusedMLPProjector(cfg.vision.feature_dim, llm_dim)
        self.language_model = build_language_model(cfg.llm, cfg.llm.vocab_size)
        # absent heads are registered as None: read by name, they are None
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

    @property
    def causal_lm(self) -> nn.Module:
        """The `LlamaForCausalLM` under `language_model`, also when peft wrapped it for LoRA (peft patches the
        layers in place). Read on each use: LoRA wraps and merges `language_model` after construction."""
        get_base = getattr(self.language_model, "get_base_model", None)
        return get_base() if callable(get_base) else self.language_model

    # --- encode: frames + memory -> visual tokens -------------------------------------------------
    def encode(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Visual tokens of a training batch: its memory (oldest first) and its current frames.

        A grounding batch may hold fewer frames than sequences: `frame_index` (B,) says which frame of
        `pixel_values` (F, 3, H, W) each sequence reads (each frame is encoded once).

        Returns:
            (B, M, D) memory tokens, their (B, M) bool mask (False on missing memory sets) and the (B, P, D)
            current-frame tokens.
        """
        current = self.projector(
            encode_frames(self.vision_backbone, batch[PIXEL_VALUES], batch.get(FRAME_INDEX))
        )  # (B, P, D)
        memory, memory_mask = self._batch_memory(batch)  # (B, M, D), (B, M)
        if memory.shape[0] != current.shape[0]:  # a grounding batch has no memory: one empty row per sequence
            memory = current.new_zeros(current.shape[0], 0, current.shape[-1])  # (B, 0, D)
            memory_mask = torch.zeros(current.shape[0], 0, dtype=torch.bool, device=current.device)
        return memory.to(current.dtype), memory_mask, current

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

    def encode_step(
        self, pixels: torch.Tensor, episodes: list[EpisodeState]
    ) -> tuple[StepFrames, list[torch.Tensor]]:
        """Visual tokens of one closed-loop step: the (B, 3, H, W) uint8 current frames (backbone features, DINO
        CLS for the ViTs, projected tokens) and each running episode's (M_i, D) memory tokens, oldest first."""
        patches, dino_cls = self.vision_backbone.forward_with_cls(pixels)  # (B, P, D_v), (B, D_dino) or None
        frames = StepFrames(patches, dino_cls, self.projector(patches))
        return frames, self.memory.read(self.vision_backbone, self.projector, episodes, frames)

    def write_memory(self, episodes: list[EpisodeState], frames: StepFrames) -> None:
        """Remember this step's frames in each episode's memory (after the episode recorded the step)."""
        self.memory.write(self.projector, episodes, frames)

    def box_token(self, boxes: torch.Tensor, visible: torch.Tensor, jitter: float = 0.0) -> torch.Tensor:
        """The BOX token's (B, D) input embedding of (B, 4) cxcywh boxes and their (B,) visibility (training: the
        true boxes, jittered by `jitter`; inference: the grounding head's)."""
        return self.box_token_embed(jitter_boxes(boxes.float(), jitter), visible.bool())

    # --- the backbone (`forward`): layout -> hidden states ---------------------------------------------
    def forward(self, layout: SequenceLayout, cache=None) -> torch.Tensor:
        """The backbone: (B, T, D) last hidden states of the layout's tokens (`network(layout, cache)`, so
        forward hooks on the network see every LLM call of training and inference).

        Right-padded training rows run in length groups (`llm.length_groups`) and never with a KV cache: under
        activation checkpointing applied from outside (FSDP's checkpoint wrapper), a recomputed decoder layer
        would append its keys to the same cache a second time. With `cache` (`new_cache`) the tokens read and
        extend it in place (an inference prefill, then its `SequenceLayout.then` steps).
        """
        if cache is not None:
            keyword = cache_keyword(type(self.causal_lm.model))
            out = self.run_llm(
                layout.embeds, layout.mask, position_ids=layout.positions, use_cache=True, **{keyword: cache}
            )
            return out.last_hidden_state
        if layout.padding == PADDING_RIGHT:
            return run_in_length_groups(
                lambda rows, rows_mask: self.run_llm(rows, rows_mask, use_cache=False).last_hidden_state,
                layout.embeds,
                layout.mask,
                self.cfg.llm.length_groups,
            )  # (B, L, D)
        return self.run_llm(
            layout.embeds, layout.mask, position_ids=layout.positions, use_cache=False
        ).last_hidden_state

    def run_llm(self, embeds: torch.Tensor, attention_mask: torch.Tensor, **kwargs) -> Any:
        """Decoder stack without the LM head -> transformers output (last_hidden_state, past_key_values)."""
        kwargs.setdefault("position_ids", position_ids_from_mask(attention_mask))
        core = self.causal_lm.model
        return core(inputs_embeds=embeds, attention_mask=attention_mask, **kwargs)

    # The cache is a transformers `DynamicCache` filled in place by every call, passed under the decoder's own
    # keyword (`cache`; `past_key_values` before transformers renamed it): no deprecated name is used and the
    # output's cache attribute is never read.
    def new_cache(self) -> Any:
        """An empty `DynamicCache` for the LLM."""
        from transformers import DynamicCache

        return DynamicCache(config=self.causal_lm.config)

    def embed_text(self, input_ids: torch.Tensor) -> torch.Tensor:
        """(B, L) ids -> (B, L, D) input embeddings."""
        return self.causal_lm.get_input_embeddings()(input_ids)

    # --- heads: hidden states -> action logits, box ------------------------------------------------------
    def cell_colours(
        self, pixels: torch.Tensor, frame_index: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        """The grounding head's colour histogram of each cell, (B, P, C + 1) (C named colours and none), of the
        (F, 3, H, W) uint8 current frames (sequence i reads frame `frame_index[i]`, default i); None when the head
        has no colour vocabulary."""
        vocabulary = getattr(self.grounding_head, "colour_vocabulary", None)
        if vocabulary is None:
            return None
        colours = vocabulary.histogram(pixels)  # (F, P, C + 1)
        return colours if frame_index is None else colours[frame_index.to(colours.device)]

    def heads(
        self,
        hidden: torch.Tensor,
        layout: SequenceLayout,
        actions: bool = True,
        boxes: bool = True,
        colours: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor | None, GroundingOutput | None]:
        """The action logits and the grounding head's output, read where the layout says.

        Args:
            hidden: (B, T, D) the backbone's output for `layout`.
            layout: training rows (the action is read before each target) or an inference step (at the last
                position).
            actions / boxes: which heads to run (None for the others, and for an absent grounding head).
            colours: (B, P, C + 1) the current frames' cell colours (`cell_colours`), for a head with a colour
                vocabulary.

        Returns:
            Float32 logits, (n, V) at the n targets of a training layout or (B, V) at the last position, and
            the `GroundingOutput`.
        """
        logits = None
        if actions:
            read = hidden[:, -1] if layout.labels is None else hidden[:, :-1][layout.action_reads()]
            logits = self.lm_logits(read)
        if not boxes or self.grounding_head is None:
            return logits, None
        readable = layout.readable
        # the colour vocabulary reads the prompt's words: (B, L) bool
        word_mask = None if colours is None else layout.prompt_mask()
        grounding = self.grounding_head(
            hidden,
            readable,
            layout.image_positions(),
            last_true_index(readable),
            layout.current,
            colours,
            None if colours is None else layout.embeds,
            word_mask,
        )
        return logits, grounding

    def lm_logits(self, hidden: torch.Tensor) -> torch.Tensor:
        """LM head on selected hidden states -> float32 logits."""
        return self.causal_lm.lm_head(hidden).float()

    def predicted_boxes(
        self, grounding: GroundingOutput | None, batch: int
    ) -> tuple[torch.Tensor, list[bool]]:
        """(B, 4) float boxes of the grounding head's output and whether each counts as visible (no head: zeros,
        not visible; no visibility training: every box counts)."""
        if grounding is None:
            return torch.zeros(batch, 4, device=self.projector.fc1.weight.device), [False] * batch
        if self.cfg.grounding.visibility_weight == 0:
            return grounding.boxes.float(), [True] * batch
        return grounding.boxes.float(), [bool(v) for v in grounding.visibility > 0]

    def decode_actions(
        self, logits: torch.Tensor, layout: SequenceLayout, cache, action_tokenizer: ActionTokenizer
    ) -> torch.Tensor:
        """Discrete head: (B, 10) logits of the action ids. Bins head: (B, 8) token ids decoded greedily from
        the (B, V) `logits` at the last position, reusing the KV `cache` of `layout` (as predict_action)."""
        if action_tokenizer.head == HEAD_DISCRETE:
            ids = torch.tensor(action_tokenizer.discrete_token_ids, device=logits.device)
            return logits[:, ids]  # (B, 10)
        token = logits.argmax(dim=-1)  # (B,)
        generated = [token]
        for _ in range(action_tokenizer.num_action_tokens - 1):
            layout = layout.then(self.embed_text(token))
            token = self.lm_logits(self(layout, cache)[:, -1]).argmax(dim=-1)
            generated.append(token)
        return torch.stack(generated, dim=1)  # (B, 8)

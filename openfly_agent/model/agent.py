"""`OpenFlyAgent`: fused ViT backbone + projector + Llama + grounding head + keyframe memory + action head.

A `transformers.PreTrainedModel`, so save / load (safetensors, sharding), AutoModel registration and
`push_to_hub` come from transformers. Inputs are prepared by `self.processor` (model/processor.py), in training
(through the collator) and in inference alike. Training: `forward(batch) -> (loss, logs)`. Closed-loop
inference, as lerobot's policies: `select_action(observations)` / `predict_step` / `reset(episode_ids)`, with
each running episode's state (model/episode.py) in `self.episodes` (model/agent_inference.py).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import torch
import torch.nn.functional as F
from transformers import PreTrainedModel
from transformers import initialization as init

from openfly_agent.constants import (
    ACTION_STOP,
    ATTENTION_MASK,
    BOX,
    BOX_VISIBLE,
    FRAME_INDEX,
    IGNORE_INDEX,
    INPUT_IDS,
    LABELS,
    MODEL_TYPE,
    PIXEL_VALUES,
    TARGET_ATTRIBUTES,
)
from openfly_agent.model.agent_inference import ClosedLoopInference
from openfly_agent.model.config import (
    HEAD_DISCRETE,
    BinsActionHeadConfig,
    DiscreteActionHeadConfig,
    ModelConfig,
)
from openfly_agent.model.episode import EpisodeState
from openfly_agent.model.factory import make_action_tokenizer, resolve_vocabulary
from openfly_agent.model.freeze import freeze
from openfly_agent.model.grounding.box_token import (
    BoxTokenEmbedding,
    insert_before_targets,
    jitter_boxes,
    last_true_index,
)
from openfly_agent.model.grounding.head import (
    GroundingOutput,
    grounding_loss,
    make_grounding_head,
)
from openfly_agent.model.grounding.layers import QueryReader
from openfly_agent.model.language.length_groups import run_in_length_groups
from openfly_agent.model.language.llm import build_language_model, unwrap_causal_lm
from openfly_agent.model.language.sequence import position_ids_from_mask, splice_after_bos
from openfly_agent.model.language.tokenizer import load_tokenizer
from openfly_agent.model.memory.encoding import MemoryEncoding
from openfly_agent.model.memory.keyframes import KeyframeSelector
from openfly_agent.model.persistence.agent_io import AgentPersistence
from openfly_agent.model.pretrained_config import OpenFlyAgentConfig
from openfly_agent.model.processor import OpenFlyProcessor
from openfly_agent.model.vision.backbone import build_vision_backbone
from openfly_agent.model.vision.conv import ConvVisionBackbone
from openfly_agent.model.vision.projector import FusedMLPProjector
from openfly_agent.utils.config import config_to_dict

logger = logging.getLogger(__name__)


class OpenFlyAgent(ClosedLoopInference, MemoryEncoding, AgentPersistence, PreTrainedModel):
    """OpenFly-Agent under OpenVLA's module names (`vision_backbone`, `projector`, `language_model`).

    Args:
        config: the transformers config (build fresh models with `from_model_config`).
        tokenizer: optional text tokenizer; with it the agent has its `processor` (needed by `select_action`).
    """

    config_class = OpenFlyAgentConfig
    base_model_prefix = ""
    main_input_name = "pixel_values"
    supports_gradient_checkpointing = True
    _no_split_modules = ["LlamaDecoderLayer", "Block", "CrossAttentionLayer"]
    _supports_sdpa = True
    _supports_flash_attn = True
    _supports_attention_backend = True

    def __init__(self, config: OpenFlyAgentConfig, tokenizer=None) -> None:
        super().__init__(config)
        cfg = config.model_config
        if cfg.llm.vocab_size is None:
            raise ValueError(
                "llm.vocab_size is unresolved: build fresh agents with "
                "OpenFlyAgent.from_model_config(cfg, tokenizer)"
            )
        self.model_cfg = cfg
        llm_dim = cfg.llm.resolved_hidden_size
        self.vision_backbone = build_vision_backbone(cfg.vision)
        self.projector = FusedMLPProjector(cfg.vision.feature_dim, llm_dim, cfg.projector.hidden_ratio)
        self.language_model = build_language_model(cfg.llm, cfg.llm.vocab_size)
        self.grounding_head = (
            make_grounding_head(llm_dim, cfg.grounding, cfg.vision.grid_side)
            if cfg.grounding.enabled
            else None
        )
        self.box_token_embed = BoxTokenEmbedding(llm_dim) if cfg.uses_box_token else None
        self.action_tokenizer = make_action_tokenizer(cfg, config.norm_stats)  # built from the config only
        config.action_tokenizer = self.action_tokenizer.to_dict()
        self.keyframe_selector = KeyframeSelector.from_config(cfg.keyframes, cfg.memory.capacity)
        self.processor: OpenFlyProcessor | None = None
        self.tokenizer = tokenizer  # builds the processor
        self.episodes: dict[str, EpisodeState] = {}  # running episodes of select_action / predict_step
        self.post_init()

    # --- construction -----------------------------------------------------------------------------
    @classmethod
    def from_model_config(
        cls, cfg: ModelConfig, tokenizer=None, norm_stats: dict | None = None
    ) -> OpenFlyAgent:
        """A freshly initialised agent; vocab size and special ids are resolved from the tokenizer.

        Args:
            cfg: model sections.
            tokenizer: text tokenizer (else loaded from `llm.tokenizer_path` when set); the tiny preset needs
                one to size its vocabulary (`len(tokenizer) + 256`).
            norm_stats: dataset statistics profiles (needed by the `openvla_bins` head).
        """
        if tokenizer is None and cfg.llm.tokenizer_path:
            tokenizer = load_tokenizer(cfg.llm.tokenizer_path)
        cfg = resolve_vocabulary(cfg, tokenizer)
        return cls(OpenFlyAgentConfig.from_model_config(cfg, norm_stats), tokenizer=tokenizer)

    @torch.no_grad()
    def _init_weights(self, module: torch.nn.Module) -> None:
        """Fresh init of the non-transformers modules (timm ViT tokens, LayerScale, box queries, tiny-cnn)."""
        from timm.layers import LayerScale
        from timm.models.vision_transformer import VisionTransformer

        super()._init_weights(module)
        if isinstance(module, VisionTransformer):
            if module.pos_embed is not None:
                init.trunc_normal_(module.pos_embed, std=0.02)
            for token in (module.cls_token, module.reg_token):
                if token is not None:
                    init.normal_(token, std=1e-6)
        elif isinstance(module, LayerScale):
            init.constant_(module.gamma, module.init_values)
        elif isinstance(module, (QueryReader, ConvVisionBackbone)):  # either grounding head, tiny-cnn
            module.init_weights()

    @property
    def tokenizer(self):
        """The text tokenizer of the processor (None: the agent has no processor)."""
        return None if self.processor is None else self.processor.tokenizer

    @tokenizer.setter
    def tokenizer(self, tokenizer) -> None:
        """Set the text tokenizer: (re)builds `processor` from the config (None removes it)."""
        self.processor = (
            None
            if tokenizer is None
            else OpenFlyProcessor.from_model_config(self.model_cfg, tokenizer, self.config.norm_stats)
        )

    def set_action_decoding(self, decode_rule: str | None = None, unnorm_key: str | None = None) -> None:
        """Change how `openvla_bins` tokens decode (rule, norm-stats profile) through the config: config.json's
        sections, `config.action_tokenizer`, the action tokenizer and the processor all follow (None: keep). The
        discrete head has one decoding: nothing changes."""
        head = self.model_cfg.action_head
        if not isinstance(head, BinsActionHeadConfig):
            return
        head = dataclasses.replace(
            head, decode_rule=decode_rule or head.decode_rule, unnorm_key=unnorm_key or head.unnorm_key
        )
        self.model_cfg = dataclasses.replace(self.model_cfg, action_head=head)
        self.config.agent = config_to_dict(self.model_cfg)
        self.action_tokenizer = make_action_tokenizer(self.model_cfg, self.config.norm_stats)
        self.config.action_tokenizer = self.action_tokenizer.to_dict()
        self.tokenizer = self.tokenizer  # rebuilds the processor from the new config

    # --- encoders ---------------------------------------------------------------------------------
    @property
    def llm_dim(self) -> int:
        """LLM hidden size."""
        return self.model_cfg.llm.resolved_hidden_size

    def embed_text(self, input_ids: torch.Tensor) -> torch.Tensor:
        """(B, L) ids -> (B, L, D) input embeddings."""
        return unwrap_causal_lm(self.language_model).get_input_embeddings()(input_ids)

    def encode_visual(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """Visual tokens of a training batch: memory (oldest first) then the current frame.

        A grounding batch may hold fewer frames than sequences: `frame_index` (B,) says which frame of
        `pixel_values` (F, 3, H, W) each sequence reads (each frame is encoded once).

        Returns:
            (B, M + P, D) tokens and their (B, M + P) bool mask (False on missing memory sets).
        """
        current = self.projector(self.encode_frames(batch[PIXEL_VALUES], batch.get(FRAME_INDEX)))  # (B, P, D)
        memory, memory_mask = self.encode_memory_batch(batch)  # (B, M, D), (B, M)
        if memory.shape[0] != current.shape[0]:  # a grounding batch has no memory: one empty row per sequence
            memory = current.new_zeros(current.shape[0], 0, current.shape[-1])  # (B, 0, D)
            memory_mask = torch.zeros(current.shape[0], 0, dtype=torch.bool, device=current.device)
        visual = torch.cat([memory.to(current.dtype), current], dim=1)  # (B, M + P, D)
        return visual, torch.cat([memory_mask, memory_mask.new_ones(current.shape[:2])], dim=1)

    def run_llm(self, embeds: torch.Tensor, attention_mask: torch.Tensor, **kwargs) -> Any:
        """Decoder stack without the LM head -> transformers output (last_hidden_state, past_key_values)."""
        kwargs.setdefault("position_ids", position_ids_from_mask(attention_mask))
        core = unwrap_causal_lm(self.language_model).model
        return core(inputs_embeds=embeds, attention_mask=attention_mask, **kwargs)

    def lm_logits(self, hidden: torch.Tensor) -> torch.Tensor:
        """LM head on selected hidden states -> float32 logits."""
        return unwrap_causal_lm(self.language_model).lm_head(hidden).float()

    # --- training ---------------------------------------------------------------------------------
    def forward(self, batch: dict[str, Any]) -> tuple[torch.Tensor, dict[str, float]]:
        """Action cross-entropy + `grounding.loss_weight` * grounding loss on a collated batch.

        A batch without `labels` is a grounding batch (the grounding stage: a referring expression or an
        instruction per sequence, the target's box, no action): only the grounding loss is computed.

        Args:
            batch: the keys of docs/INTERFACES.md (input_ids, attention_mask, labels, pixel_values, memory_*,
                box, box_visible, frame_index), as `data/collator.py` builds them with `self.processor`.

        Returns:
            The scalar loss and float logs: loss, action_loss, grounding_loss, action_accuracy, box_iou,
            num_visible_boxes.
        """
        input_ids = batch[INPUT_IDS]
        bos = self.model_cfg.llm.bos_token_id
        if not bool((input_ids[:, 0] == bos).all()):
            raise ValueError(
                f"input_ids must start with BOS ({bos}) in column 0 (right padding); got {input_ids[:, 0]}"
            )
        labels = batch.get(LABELS)
        if labels is None:
            labels = torch.full_like(input_ids, IGNORE_INDEX)
        visual, visual_mask = self.encode_visual(batch)
        embeds, mask, labels = splice_after_bos(
            self.embed_text(input_ids), batch[ATTENTION_MASK], labels, visual, visual_mask
        )  # [BOS] [memory] [current] [prompt] [action]: (B, L', D), (B, L'), (B, L')
        readable = mask.bool() & (labels == IGNORE_INDEX)  # what the grounding head may read: no targets
        has_actions = bool((labels != IGNORE_INDEX).any())
        if self.box_token_embed is not None and has_actions:
            box = jitter_boxes(
                batch[BOX].float(), self.model_cfg.action_head.box_token_jitter if self.training else 0
            )
            token = self.box_token_embed(box, batch[BOX_VISIBLE].bool())  # (B, D)
            embeds, mask, labels, at = insert_before_targets(embeds, mask, labels, token)
            readable = mask.bool() & (labels == IGNORE_INDEX)
            readable[torch.arange(readable.shape[0], device=readable.device), at] = False
        # no KV cache in training: under activation checkpointing applied from outside (FSDP's checkpoint
        # wrapper), a recomputed decoder layer would append its keys to the same cache a second time
        hidden = run_in_length_groups(
            lambda rows, rows_mask: self.run_llm(rows, rows_mask, use_cache=False).last_hidden_state,
            embeds,
            mask,
            self.model_cfg.llm.length_groups,
        )  # (B, L', D)
        loss = hidden.new_zeros(())
        logs = {}
        if has_actions:
            action_loss, accuracy = self._action_loss(hidden, labels)
            loss = loss + action_loss
            logs.update(action_loss=float(action_loss.detach()), action_accuracy=accuracy)
        if self.grounding_head is not None and BOX in batch:
            first_image = visual.shape[1] - self.model_cfg.vision.num_patches + 1  # after BOS and the memory
            output = self.ground(
                hidden, readable, first_image, visual[:, -self.model_cfg.vision.num_patches :]
            )
            targets = batch[BOX], batch[BOX_VISIBLE].bool()  # (B, 4), (B,)
            g_loss, g_logs = grounding_loss(
                output, *targets, self.model_cfg.grounding, batch.get(TARGET_ATTRIBUTES)
            )
            loss = loss + self.model_cfg.grounding.loss_weight * g_loss
            logs.update(g_logs, grounding_loss=float(g_loss.detach()))
        else:
            # no head, no box measured: NaN, which the running means and the evaluation leave out (not a 0 IoU)
            logs.update(grounding_loss=0.0, box_iou=float("nan"), num_visible_boxes=0.0)
        if not has_actions and self.grounding_head is None:
            raise ValueError("batch has no labelled action token and the agent has no grounding head")
        logs["loss"] = float(loss.detach())
        return loss, logs

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
        p = self.model_cfg.vision.num_patches
        first = torch.as_tensor(first_image, device=hidden.device).reshape(-1, 1)  # (B or 1, 1)
        image_positions = (first + torch.arange(p, device=hidden.device)[None]).expand(hidden.shape[0], p)
        return self.grounding_head(hidden, readable, image_positions, last_true_index(readable), current)

    def _action_loss(self, hidden: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, float]:
        targets = labels[:, 1:]  # next-token targets
        selected = targets != IGNORE_INDEX  # (B, L'-1)
        if not bool(selected.any()):
            raise ValueError("batch has no labelled action token: labels are all -100")
        logits = self.lm_logits(hidden[:, :-1][selected])  # (n, V), only where a label exists
        target = targets[selected]  # (n,)
        head = self.model_cfg.action_head
        stop_weight = head.stop_loss_weight if isinstance(head, DiscreteActionHeadConfig) else 1.0
        if stop_weight == 1.0:
            loss = F.cross_entropy(logits, target)
        else:  # a weighted mean: STOP-labelled steps count stop_weight times (discrete head, config-checked)
            stop_id = self.action_tokenizer.action_to_token_ids(ACTION_STOP)[0]
            weights = torch.where(target == stop_id, stop_weight, 1.0).to(logits.dtype)  # (n,)
            per_token = F.cross_entropy(logits, target, reduction="none")  # (n,)
            loss = (per_token * weights).sum() / weights.sum()
        with torch.no_grad():
            if self.action_tokenizer.head == HEAD_DISCRETE:
                ids = torch.tensor(self.action_tokenizer.discrete_token_ids, device=logits.device)
                predicted = ids[logits[:, ids].argmax(dim=-1)]  # argmax over the 10 actions, as select_action
            else:
                predicted = logits.argmax(dim=-1)
            is_action = (target >= self.action_tokenizer.action_token_begin) & (
                target < self.action_tokenizer.vocab_end
            )
            accuracy = (
                float((predicted == target)[is_action].float().mean()) if bool(is_action.any()) else 0.0
            )
        return loss, accuracy

    # --- training set-up ---------------------------------------------------------------------------
    def freeze(self, stage: str) -> dict[str, int]:
        """Apply a named freeze stage (`full`, `frozen_vision`, `heads_only`, `lora`); see model/freeze.py."""
        return freeze(self, stage)

    def _set_gradient_checkpointing(self, enable: bool = True, **kwargs) -> None:
        """transformers' activation checkpointing on the Llama layers, plus timm's on both ViTs."""
        super()._set_gradient_checkpointing(enable=enable, **kwargs)
        self.vision_backbone.set_grad_checkpointing(enable)

    def get_optim_params(self, weight_decay: float = 0.0) -> list[dict]:
        """Trainable parameters in two AdamW groups: decay on matrices, none on biases / norms / tokens."""
        decay, no_decay = [], []
        for name, param in self.named_parameters():
            if param.requires_grad:
                tokens = any(key in name for key in ("pos_embed", "cls_token", "reg_token", "box_queries"))
                (no_decay if param.ndim < 2 or tokens else decay).append(param)
        return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]


def register_auto_classes() -> None:
    """Register the agent with transformers' AutoConfig / AutoModel / AutoProcessor (call once from an entry
    point; folders saved by the agent also load with `trust_remote_code=True` without it)."""
    from transformers import AutoConfig, AutoModel, AutoProcessor

    AutoConfig.register(MODEL_TYPE, OpenFlyAgentConfig, exist_ok=True)
    AutoModel.register(OpenFlyAgentConfig, OpenFlyAgent, exist_ok=True)
    AutoProcessor.register(OpenFlyAgentConfig, OpenFlyProcessor, exist_ok=True)

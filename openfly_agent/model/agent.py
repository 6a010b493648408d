"""`OpenFlyAgent`: fused ViT backbone + projector + Llama + grounding head + keyframe memory + action head.

A `transformers.PreTrainedModel`, so save / load (safetensors, sharding), AutoModel registration and
`push_to_hub` come from transformers. Training: `forward(batch) -> (loss, logs)`; closed-loop inference:
`select_action(observations)` / `reset(episode_ids)` (model/inference.py).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from transformers import PreTrainedModel
from transformers import initialization as init

from openfly_agent.constants import (
    ACTION_TOKENIZER_NAME,
    ATTENTION_MASK,
    BOX,
    BOX_VISIBLE,
    IGNORE_INDEX,
    INPUT_IDS,
    LABELS,
    MEMORY_BOX_VISIBLE,
    MEMORY_BOXES,
    MEMORY_FRAME_MASK,
    MEMORY_PIXEL_VALUES,
    NORM_STATS_NAME,
    PIXEL_VALUES,
)

from .config import (
    HEAD_DISCRETE,
    MODE_OPENVLA_COMPAT,
    ModelConfig,
)
from .pretrained_config import OpenFlyAgentConfig
from .factory import make_action_tokenizer, resolve_vocabulary
from .freeze import freeze
from .grounding import GroundingHead, grounding_loss
from .inference import StepResult, predict_step, reset_episodes
from .keyframes import KeyframeSelector
from .llm import build_language_model, unwrap_causal_lm
from .memory import grid_pool
from .merging import choose_reference, merge_into_reference
from .projector import FusedMLPProjector
from .sequence import position_ids_from_mask, splice_after_bos
from .vision import FusedVisionBackbone

logger = logging.getLogger(__name__)


class OpenFlyAgent(PreTrainedModel):
    """OpenFly-Agent under OpenVLA's module names (`vision_backbone`, `projector`, `language_model`).

    Args:
        config: the transformers config (build fresh models with `from_model_config`).
        tokenizer: optional text tokenizer, saved with the model and used by `select_action`.
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
        self.vision_backbone = FusedVisionBackbone(cfg.vision)
        self.projector = FusedMLPProjector(cfg.vision.feature_dim, llm_dim, cfg.projector.hidden_ratio)
        self.language_model = build_language_model(cfg.llm, cfg.llm.vocab_size)
        self.grounding_head = GroundingHead(llm_dim, cfg.grounding) if cfg.grounding.enabled else None
        self.action_tokenizer = make_action_tokenizer(cfg, config.norm_stats)
        config.action_tokenizer = self.action_tokenizer.to_dict()
        self.keyframe_selector = KeyframeSelector(
            capacity=cfg.memory.capacity,
            theta=cfg.keyframes.theta,
            radius=cfg.keyframes.radius,
            merge_forward=cfg.keyframes.merge_forward,
        )
        self.tokenizer = tokenizer
        self.episodes: dict = {}  # episode_id -> inference state (model/inference.py)
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
            from .tokenizer import load_tokenizer

            tokenizer = load_tokenizer(cfg.llm.tokenizer_path)
        cfg = resolve_vocabulary(cfg, tokenizer)
        return cls(OpenFlyAgentConfig.from_model_config(cfg, norm_stats), tokenizer=tokenizer)

    @torch.no_grad()
    def _init_weights(self, module: torch.nn.Module) -> None:
        """Fresh init of the non-transformers modules (timm ViT tokens, LayerScale, box queries)."""
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
        elif isinstance(module, GroundingHead):
            init.normal_(module.box_queries, std=0.02)

    # --- processor pieces used by the collator ------------------------------------------------------------
    def image_transform(self, rgb: np.ndarray) -> torch.Tensor:
        """(H, W, 3) uint8 RGB -> (3, s, s) uint8 at the model's input size (bicubic as OpenVLA, or area)."""
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"image_transform expects (H, W, 3) uint8 RGB, got {rgb.dtype} {rgb.shape}")
        size = self.model_cfg.vision.image_size
        if rgb.shape[:2] != (size, size):
            if self.model_cfg.vision.resize == "bicubic":
                from PIL import Image

                rgb = np.asarray(Image.fromarray(rgb).resize((size, size), Image.BICUBIC))
            else:
                import cv2

                rgb = cv2.resize(rgb, (size, size), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(np.array(rgb, dtype=np.uint8, copy=True)).permute(2, 0, 1).contiguous()

    def build_prompt(self, instruction: str) -> str:
        """The text after the visual tokens for `instruction` (template of the `prompt` section)."""
        text = instruction.strip()
        if self.model_cfg.prompt.lowercase:
            text = text.lower()
        return self.model_cfg.prompt.template.format(instruction=text)

    # --- encoders ---------------------------------------------------------------------------------
    @property
    def llm_dim(self) -> int:
        """LLM hidden size."""
        return self.model_cfg.llm.resolved_hidden_size

    def embed_text(self, input_ids: torch.Tensor) -> torch.Tensor:
        """(B, L) ids -> (B, L, D) input embeddings."""
        return unwrap_causal_lm(self.language_model).get_input_embeddings()(input_ids)

    def memory_set_tokens(
        self, features: torch.Tensor, frame_mask: torch.Tensor, boxes: torch.Tensor, box_visible: torch.Tensor
    ) -> torch.Tensor:
        """Keyframe sets -> memory tokens: merge into the largest-box frame, grid-pool, project.

        Args:
            features: (N, S, P, D_v) fused features of each frame of each set.
            frame_mask: (N, S) bool, real frames.
            boxes: (N, S, 4) landmark boxes (ground truth in training, predicted online).
            box_visible: (N, S) bool.

        Returns:
            (N, (sqrt(P) / g)^2, D_llm) tokens.
        """
        reference = choose_reference(boxes.to(features.device), box_visible.to(features.device), frame_mask)
        merging = self.model_cfg.merging
        if merging.enabled:
            merged = merge_into_reference(features, frame_mask, reference, merging.threshold, merging.top_r)
        else:
            merged = features[
                torch.arange(features.shape[0], device=features.device), reference
            ]  # (N, P, D_v)
        return self.projector(grid_pool(merged, self.model_cfg.memory.grid))  # (N, m, D)

    def history_tokens(self, patches: torch.Tensor, dino_cls: torch.Tensor) -> torch.Tensor:
        """openvla_compat: one token per history frame = DINO CLS ++ pooled SigLIP patches -> (N, D_llm)."""
        siglip = patches[..., self.vision_backbone.dino_dim :]  # (N, P, D_siglip)
        pooled = grid_pool(siglip, self.model_cfg.memory.grid)[:, 0]  # (N, D_siglip)
        return self.projector(torch.cat([dino_cls, pooled], dim=-1))  # (N, D)

    def encode_memory_batch(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """Memory tokens of a training batch -> (B, M, D) tokens and (B, M) bool mask (missing sets off)."""
        current = batch[PIXEL_VALUES]
        b = current.shape[0]
        if self.model_cfg.memory.capacity == 0 or MEMORY_PIXEL_VALUES not in batch:
            empty = torch.zeros(
                b, 0, self.llm_dim, device=current.device, dtype=self.projector.fc1.weight.dtype
            )
            return empty, torch.zeros(b, 0, dtype=torch.bool, device=current.device)
        pixels = batch[MEMORY_PIXEL_VALUES]  # (B, K, S, 3, H, W)
        frame_mask = batch[MEMORY_FRAME_MASK].bool().to(pixels.device)  # (B, K, S)
        _, k, s = pixels.shape[:3]
        if k > self.model_cfg.memory.capacity:
            raise ValueError(
                f"batch holds {k} memory sets but memory.capacity is {self.model_cfg.memory.capacity}"
            )
        real = pixels[frame_mask]  # (n_real, 3, H, W)
        if self.model_cfg.mode == MODE_OPENVLA_COMPAT:
            tokens = self.projector.fc3.weight.new_zeros(b, k * s, self.llm_dim)  # (B, K*S, D)
            if real.shape[0]:
                tokens[frame_mask.view(b, k * s)] = self.history_tokens(
                    *self.vision_backbone.forward_with_cls(real)
                )
            return tokens, frame_mask.view(b, k * s)
        p, dv = self.model_cfg.vision.num_patches, self.model_cfg.vision.feature_dim
        features = self.projector.fc1.weight.new_zeros(b, k, s, p, dv)  # (B, K, S, P, D_v)
        if real.shape[0]:
            features[frame_mask] = self.vision_backbone(real).to(features.dtype)
        tokens = self.memory_set_tokens(
            features.flatten(0, 1),
            frame_mask.flatten(0, 1),
            batch[MEMORY_BOXES].flatten(0, 1),
            batch[MEMORY_BOX_VISIBLE].bool().flatten(0, 1),
        )  # (B*K, m, D)
        m = tokens.shape[1]
        set_mask = frame_mask.any(dim=-1).repeat_interleave(m, dim=1)  # (B, K*m)
        return tokens.reshape(b, k * m, -1), set_mask

    def encode_visual(self, batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """Visual tokens of a training batch: memory (oldest first) then the current frame.

        Returns:
            (B, M + P, D) tokens and their (B, M + P) bool mask (False on missing memory sets).
        """
        current = self.projector(self.vision_backbone(batch[PIXEL_VALUES]))  # (B, P, D)
        memory, memory_mask = self.encode_memory_batch(batch)  # (B, M, D), (B, M)
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

        Args:
            batch: the keys of docs/INTERFACES.md (input_ids, attention_mask, labels, pixel_values, memory_*,
                box, box_visible).

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
        visual, visual_mask = self.encode_visual(batch)
        embeds, mask, labels = splice_after_bos(
            self.embed_text(input_ids), batch[ATTENTION_MASK], batch[LABELS], visual, visual_mask
        )
        hidden = self.run_llm(embeds, mask).last_hidden_state  # (B, L', D)
        action_loss, accuracy = self._action_loss(hidden, labels)
        loss = action_loss
        logs = {"action_loss": float(action_loss.detach()), "action_accuracy": accuracy}
        if self.grounding_head is not None and BOX in batch:
            boxes, visibility = self.grounding_head(hidden, mask.bool() & (labels == IGNORE_INDEX))
            g_loss, g_logs = grounding_loss(
                boxes, visibility, batch[BOX], batch[BOX_VISIBLE].bool(), self.model_cfg.grounding
            )
            loss = loss + self.model_cfg.grounding.loss_weight * g_loss
            logs.update(g_logs, grounding_loss=float(g_loss.detach()))
        else:
            logs.update(grounding_loss=0.0, box_iou=0.0, num_visible_boxes=0.0)
        logs["loss"] = float(loss.detach())
        return loss, logs

    def _action_loss(self, hidden: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, float]:
        targets = labels[:, 1:]  # next-token targets
        selected = targets != IGNORE_INDEX  # (B, L'-1)
        if not bool(selected.any()):
            raise ValueError("batch has no labelled action token: labels are all -100")
        logits = self.lm_logits(hidden[:, :-1][selected])  # (n, V), only where a label exists
        target = targets[selected]  # (n,)
        loss = F.cross_entropy(logits, target)
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

    # --- closed-loop inference (model/inference.py) -----------------------------------------------
    def select_action(self, observations: list[dict[str, Any]]) -> list[int]:
        """One action per observation, all episodes in one batch, each with its own memory.

        Args:
            observations: dicts with `episode_id`, `instruction`, `rgb` ((H, W, 3) uint8) and `pose`.

        Returns:
            Action ids 0..9, in the order of `observations`.
        """
        return [result.action for result in predict_step(self, observations)]

    def predict_step(self, observations: list[dict[str, Any]]) -> list[StepResult]:
        """`select_action` with details: action logits (or bin tokens) and the predicted landmark box."""
        return predict_step(self, observations)

    def reset(self, episode_ids: list[str] | None = None) -> None:
        """Forget the memory of the listed episodes (every episode when None)."""
        reset_episodes(self, episode_ids)

    # --- training set-up ---------------------------------------------------------------------------
    def freeze(self, stage: str) -> dict[str, int]:
        """Apply a named freeze stage (`full`, `frozen_vision`, `heads_only`, `lora`); see model/freeze.py."""
        return freeze(self, stage)

    def _set_gradient_checkpointing(self, enable: bool = True, **kwargs) -> None:
        """transformers' activation checkpointing on the Llama layers, plus timm's on both ViTs."""
        super()._set_gradient_checkpointing(enable=enable, **kwargs)
        self.vision_backbone.featurizer.set_grad_checkpointing(enable)
        self.vision_backbone.fused_featurizer.set_grad_checkpointing(enable)

    def get_optim_params(self, weight_decay: float = 0.0) -> list[dict]:
        """Trainable parameters in two AdamW groups: decay on matrices, none on biases / norms / tokens."""
        decay, no_decay = [], []
        for name, param in self.named_parameters():
            if param.requires_grad:
                tokens = any(key in name for key in ("pos_embed", "cls_token", "reg_token", "box_queries"))
                (no_decay if param.ndim < 2 or tokens else decay).append(param)
        return [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]

    # --- persistence ------------------------------------------------------------------------------
    def save_pretrained(self, save_directory, *args, **kwargs) -> None:
        """transformers' save (config.json + safetensors) + action_tokenizer.json, norm stats, tokenizer."""
        if getattr(self.language_model, "peft_config", None) is not None:
            raise ValueError(
                "LoRA is attached: merge it first (model.lora.merge_lora) or save the adapter "
                "(model.lora.save_lora_adapter); the merged agent saves in the plain key layout"
            )
        # transformers would upload before the extra files exist: push the finished folder afterwards instead
        push = kwargs.pop("push_to_hub", False)
        hub = {k: kwargs.pop(k) for k in ("repo_id", "commit_message", "create_pr", "private") if k in kwargs}
        super().save_pretrained(save_directory, *args, **kwargs)
        if not kwargs.get("is_main_process", True):
            return
        folder = Path(save_directory)
        self.action_tokenizer.save(folder / ACTION_TOKENIZER_NAME)
        if self.config.norm_stats:
            (folder / NORM_STATS_NAME).write_text(json.dumps(self.config.norm_stats, indent=2) + "\n")
        if self.tokenizer is not None:
            self.tokenizer.save_pretrained(str(folder))
        if push:
            hub.update({k: kwargs[k] for k in ("token", "max_shard_size") if k in kwargs})
            self.push_to_hub(hub.pop("repo_id", folder.name), **hub)

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path, *args, tokenizer=None, **kwargs):
        """transformers' load; the tokenizer saved beside the weights is loaded too (folder or Hub repo id)."""
        loaded = super().from_pretrained(pretrained_model_name_or_path, *args, **kwargs)
        model = loaded[0] if isinstance(loaded, tuple) else loaded
        if tokenizer is None:
            folder = _tokenizer_folder(str(pretrained_model_name_or_path), kwargs)
            if folder is not None:
                from .tokenizer import load_tokenizer

                tokenizer = load_tokenizer(folder)
        model.tokenizer = tokenizer
        return loaded


# Files a saved tokenizer may consist of (ours: tokenizer.json; Llama-2's: tokenizer.model).
_TOKENIZER_FILES = ["tokenizer*", "special_tokens_map.json", "added_tokens.json", "vocab*", "merges.txt"]


def _tokenizer_folder(name_or_path: str, hub_kwargs: dict) -> Path | None:
    """Local folder holding the checkpoint's tokenizer, fetching only the tokenizer files of a Hub repo id
    (with the same revision / token / cache arguments as the weights). None when the checkpoint has none."""
    folder = Path(name_or_path)
    if folder.is_dir():
        return folder if (folder / "tokenizer_config.json").is_file() else None
    from huggingface_hub import snapshot_download

    snapshot = Path(
        snapshot_download(
            name_or_path,
            revision=hub_kwargs.get("revision"),
            cache_dir=hub_kwargs.get("cache_dir"),
            token=hub_kwargs.get("token"),
            local_files_only=bool(hub_kwargs.get("local_files_only", False)),
            allow_patterns=_TOKENIZER_FILES,
        )
    )
    return snapshot if (snapshot / "tokenizer_config.json").is_file() else None


def register_auto_classes() -> None:
    """Register the agent with transformers' AutoConfig / AutoModel (call once from an entry point)."""
    from transformers import AutoConfig, AutoModel

    from openfly_agent.constants import MODEL_TYPE

    AutoConfig.register(MODEL_TYPE, OpenFlyAgentConfig, exist_ok=True)
    AutoModel.register(OpenFlyAgentConfig, OpenFlyAgent, exist_ok=True)

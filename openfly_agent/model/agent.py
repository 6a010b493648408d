"""`OpenFlyAgent`: the network (model/network.py) with its loss, processor, action tokenizer and save / load.

A `transformers.PreTrainedModel`, so save / load (safetensors, sharding), AutoModel registration and
`push_to_hub` come from transformers; config.json's model sections (`config.agent`) are the one configuration.
Inputs are prepared by `self.processor` (model/processor.py), in training (through the collator) and in
inference alike. Training: `forward(batch) -> (loss, logs)`. Closed-loop inference runs in the `AgentSession` of
`new_session()` (model/session.py), which holds the running episodes.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from transformers import PreTrainedModel
from transformers import initialization as init

from openfly_agent.constants import (
    ATTENTION_MASK,
    BOX,
    BOX_VISIBLE,
    FRAME_INDEX,
    IGNORE_INDEX,
    INPUT_IDS,
    LABELS,
    MEMORY_PROBE_NONE,
    MODEL_TYPE,
    PIXEL_VALUES,
    TARGET_ATTRIBUTES,
    TOKEN_BOX,
    TOKEN_BOX_VISIBLE,
)
from openfly_agent.model.config import (
    HEAD_DISCRETE,
    BinsActionHeadConfig,
    ModelConfig,
)
from openfly_agent.model.factory import make_action_tokenizer, resolve_vocabulary
from openfly_agent.model.freeze import freeze
from openfly_agent.model.grounding.head import grounding_loss
from openfly_agent.model.grounding.layers import QueryReader
from openfly_agent.model.language.tokenizer import load_tokenizer
from openfly_agent.model.layout import SequenceLayout
from openfly_agent.model.network import OpenFlyNetwork
from openfly_agent.model.persistence.agent_io import (
    check_no_lora,
    loadable_checkpoint,
    save_processor_files,
    saved_tokenizer,
)
from openfly_agent.model.persistence.remote_code import write_remote_code
from openfly_agent.model.persistence.saved_names import accept_saved_names, register_saved_names
from openfly_agent.model.pretrained_config import OpenFlyAgentConfig
from openfly_agent.model.processor import OpenFlyProcessor
from openfly_agent.model.session import AgentSession
from openfly_agent.model.vision.conv import ConvVisionBackbone
from openfly_agent.utils.config import config_to_dict

logger = logging.getLogger(__name__)
register_saved_names(MODEL_TYPE)  # weights files keep `vision_backbone.*`, ...: no `network.` on disk


class OpenFlyAgent(PreTrainedModel):
    """OpenFly-Agent under OpenVLA's module names (`vision_backbone`, `projector`, `language_model`).

    The agent's modules are its network's: `self._modules` is `self.network._modules` (one dict, no `network.`
    child), so the state-dict keys stay `vision_backbone.*`, `language_model.*`, ... (checkpoints written before
    the network was its own module load unchanged) and a module replaced on one (LoRA's wrapper) is on both.

    Args:
        config: the transformers config (build fresh models with `from_model_config`).
        tokenizer: optional text tokenizer; with it the agent has its `processor` (needed by `AgentSession`).
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
        self._parsed_config: tuple[dict, ModelConfig] = (dict(config.agent), cfg)
        self.network = OpenFlyNetwork(cfg)
        self.register_load_state_dict_pre_hook(accept_saved_names)  # resume files written before the child
        self._build_action_tokenizer()
        self.processor: OpenFlyProcessor | None = None
        self.tokenizer = tokenizer  # builds the processor
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

    # --- the one configuration --------------------------------------------------------------------
    @property
    def model_cfg(self) -> ModelConfig:
        """The typed model sections of `config.agent` (parsed again only after the dict changed)."""
        agent = self.config.agent
        if self._parsed_config[0] != agent:
            self._parsed_config = (dict(agent), self.config.model_config)
        return self._parsed_config[1]

    def _build_action_tokenizer(self) -> None:
        """The action tokenizer of the config; `config.action_tokenizer` records its settings in config.json."""
        self.action_tokenizer = make_action_tokenizer(self.model_cfg, self.config.norm_stats)
        self.config.action_tokenizer = self.action_tokenizer.to_dict()

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
        """Change how `openvla_bins` tokens decode (rule, norm-stats profile) in the config; the action
        tokenizer and the processor are rebuilt from it (None: keep)."""
        head = self.model_cfg.action_head
        if not isinstance(head, BinsActionHeadConfig):
            return
        head = dataclasses.replace(
            head, decode_rule=decode_rule or head.decode_rule, unnorm_key=unnorm_key or head.unnorm_key
        )
        self.config.agent = config_to_dict(dataclasses.replace(self.model_cfg, action_head=head))
        self._build_action_tokenizer()
        self.tokenizer = self.tokenizer  # rebuilds the processor from the new config

    # --- training ---------------------------------------------------------------------------------
    def forward(
        self, batch: dict[str, Any], outputs: dict[str, torch.Tensor] | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Action cross-entropy + `grounding.loss_weight` * grounding loss on a collated batch.

        A batch without `labels` is a grounding batch (the grounding stage: a referring expression or an
        instruction per sequence, the target's box, no action): only the grounding loss is computed.

        Args:
            batch: the keys of docs/INTERFACES.md (input_ids, attention_mask, labels, pixel_values, memory_*,
                box, box_visible, frame_index), as `data/collator.py` builds them with `self.processor`.

        Returns:
            The scalar loss and float logs: loss, action_loss, grounding_loss, action_accuracy, box_iou,
            num_visible_boxes.

        `outputs` (the RL stage, training/rl_trainer.py), when given, receives the tensors behind the loss:
        `action_logits` (n, V) at the positions before the n labelled tokens (row-major order), `action_targets`
        (n,) and `grounding_loss` (scalar). A batch with `token_box` / `token_box_visible` embeds that box in the
        box token instead of `box` (which stays the grounding target).
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
        has_actions = bool((labels != IGNORE_INDEX).any())
        network = self.network
        memory, memory_mask, current = network.encode(batch)  # (B, M, D), (B, M), (B, P, D)
        box = None  # the BOX token: the true box, jittered in training
        if network.box_token_embed is not None and has_actions:
            jitter = self.model_cfg.action_head.box_token_jitter if self.training else 0
            # the true box; the RL stage's replay gives the box the policy predicted (`token_box`)
            token_box = batch.get(TOKEN_BOX, batch[BOX])
            box = network.box_token(
                token_box, batch.get(TOKEN_BOX_VISIBLE, batch[BOX_VISIBLE]), jitter
            )  # (B, D)
        layout = SequenceLayout.for_training(
            network.embed_text(input_ids), batch[ATTENTION_MASK], labels, memory, memory_mask, current, box
        )  # [BOS] [memory] [current] [prompt] [BOX] [action]: (B, L', D)
        hidden = network(layout)  # (B, L', D)
        grounds = network.grounding_head is not None and BOX in batch
        colours = network.cell_colours(batch[PIXEL_VALUES], batch.get(FRAME_INDEX)) if grounds else None
        # colours: (B, P, C + 1) with a colour vocabulary, else None
        logits, grounding = network.heads(hidden, layout, has_actions, grounds, colours)
        loss = hidden.new_zeros(())
        logs = {}
        if has_actions:
            action_loss, accuracy = self._action_loss(logits, layout.action_targets(), outputs)
            loss = loss + action_loss
            logs.update(action_loss=float(action_loss.detach()), action_accuracy=accuracy)
        if grounds:
            targets = batch[BOX], batch[BOX_VISIBLE].bool()  # (B, 4), (B,)
            g_loss, g_logs = grounding_loss(
                grounding, *targets, self.model_cfg.grounding, batch.get(TARGET_ATTRIBUTES)
            )
            loss = loss + self.model_cfg.grounding.loss_weight * g_loss
            if outputs is not None:
                outputs["grounding_loss"] = g_loss
            logs.update(g_logs, grounding_loss=float(g_loss.detach()))
        else:
            # no head, no box measured: NaN, which the running means and the evaluation leave out (not a 0 IoU)
            logs.update(grounding_loss=0.0, box_iou=float("nan"), num_visible_boxes=0.0)
        if not has_actions and network.grounding_head is None:
            raise ValueError("batch has no labelled action token and the agent has no grounding head")
        logs["loss"] = float(loss.detach())
        return loss, logs

    def _action_loss(
        self, logits: torch.Tensor, target: torch.Tensor, outputs: dict | None = None
    ) -> tuple[torch.Tensor, float]:
        """Cross-entropy and accuracy of (n, V) float logits against their (n,) targets; with
        `outputs`, both tensors are also put there (`action_logits`, `action_targets`)."""
        if outputs is not None:
            outputs.update(action_logits=logits, action_targets=target)
        loss = F.cross_entropy(logits, target)
        hits, is_action = self.action_hits(logits, target)
        accuracy = float(hits[is_action].float().mean()) if bool(is_action.any()) else 0.0
        return loss, accuracy

    @torch.no_grad()
    def action_hits(self, logits: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Which of (n, V) logits predict their (n,) target token, and which targets are action tokens (the
        accuracy counts those only): two (n,) bool tensors. The discrete head predicts the argmax over its 10
        action tokens, as `select_action` does."""
        if self.action_tokenizer.head == HEAD_DISCRETE:
            ids = torch.tensor(self.action_tokenizer.discrete_token_ids, device=logits.device)
            predicted = ids[logits[:, ids].argmax(dim=-1)]  # (n,)
        else:
            predicted = logits.argmax(dim=-1)  # (n,)
        is_action = (target >= self.action_tokenizer.action_token_begin) & (
            target < self.action_tokenizer.vocab_end
        )
        return predicted == target, is_action

    def new_session(self, memory_probe: str = MEMORY_PROBE_NONE) -> AgentSession:
        """A closed-loop session of this agent (model/session.py): running episodes, `select_action`, `reset`;
        `memory_probe="empty"` reads no memory at any step (an evaluation diagnostic)."""
        return AgentSession(self, memory_probe)

    # --- persistence ------------------------------------------------------------------------------
    def save_pretrained(self, save_directory, *args, **kwargs) -> None:
        """transformers' save (config.json + safetensors), then the processor files and the remote code."""
        check_no_lora(self)
        # transformers would upload before the extra files exist: push the finished folder afterwards instead
        push = kwargs.pop("push_to_hub", False)
        hub = {k: kwargs.pop(k) for k in ("repo_id", "commit_message", "create_pr", "private") if k in kwargs}
        super().save_pretrained(save_directory, *args, **kwargs)
        if not kwargs.get("is_main_process", True):
            return
        folder = Path(save_directory)
        save_processor_files(self, folder)
        write_remote_code(folder)
        if push:
            hub.update({k: kwargs[k] for k in ("token", "max_shard_size") if k in kwargs})
            self.push_to_hub(hub.pop("repo_id", folder.name), **hub)

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path, *args, tokenizer=None, **kwargs):
        """transformers' load, plus the tokenizer saved beside the weights (folder or Hub repo id).

        Also takes a training run folder, `<run>/checkpoints` or the `checkpoints/last` pointer: they load the
        newest checkpoint. A LoRA checkpoint (`adapter/`, no weights) raises with what to load instead; a
        truncated or corrupt weights file raises `UnreadableWeightsError` naming it.
        """
        name = loadable_checkpoint(str(pretrained_model_name_or_path))
        loaded = super().from_pretrained(name, *args, **kwargs)
        model = loaded[0] if isinstance(loaded, tuple) else loaded
        model.tokenizer = tokenizer if tokenizer is not None else saved_tokenizer(name, kwargs)
        return loaded

    # --- training set-up ---------------------------------------------------------------------------
    def freeze(self, stage: str) -> dict[str, int]:
        """Apply a named freeze stage (`full`, `frozen_vision`, `heads_only`, `lora`); see model/freeze.py."""
        return freeze(self, stage)

    def _set_gradient_checkpointing(self, enable: bool = True, **kwargs) -> None:
        """transformers' activation checkpointing on the Llama layers, plus timm's on both ViTs."""
        super()._set_gradient_checkpointing(enable=enable, **kwargs)
        self.network.vision_backbone.set_grad_checkpointing(enable)

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

"""`OpenFlyProcessor`: every model input is prepared here, for training and for inference alike.

As OpenVLA's `PrismaticProcessor`, a `transformers.ProcessorMixin`: it holds the text tokenizer, the image
transform of the vision config, the prompt template and suffix, the text length limit, and the action tokenizer
with its norm statistics. The training collator (`data/collator.py`) and `OpenFlyAgent.predict_step` both call
`image` and `encode`, so BOS, suffix and truncation follow one set of rules:

    input_ids = [BOS] tokens(prompt) [suffix] [action tokens]     labels = -100 ... -100 [action tokens]

BOS is prepended when the tokenizer did not add it; the suffix (OpenVLA's '▁' 29871 for the released model)
is appended when configured; without an action (inference, or a sample with no action target) the text ends
after the prompt. When prompt + action exceed `max_length`, the prompt is cut from its end so the action
tokens always fit. Saved as `processor_config.json` (+ the tokenizer files) in every checkpoint and release.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from transformers import BatchFeature
from transformers.processing_utils import ProcessorMixin

from openfly_agent.constants import ATTENTION_MASK, IGNORE_INDEX, INPUT_IDS, LABELS, PIXEL_VALUES
from openfly_agent.model.config import RESIZE_MODES, ModelConfig, PromptConfig
from openfly_agent.model.factory import action_stats_of, make_action_tokenizer
from openfly_agent.model.language.action_tokenizer import ActionTokenizer

DEFAULT_TEMPLATE = PromptConfig().template
DEFAULT_GROUNDING_TEMPLATE = PromptConfig().grounding_template


@dataclass(frozen=True)
class ImageTransform:
    """Square resize to `size` with PIL bicubic (as OpenVLA's "resize-naive") or OpenCV area interpolation: the
    image preprocessing of a vision config, RGB frame (H, W, 3) uint8 -> model pixels (3, s, s) uint8.

    Built from the vision section (`image_size`, `resize`), so a new backbone preset brings its preprocessing with
    its config. Normalisation is not done here: each backbone normalises the uint8 pixels it receives.

    Args:
        size: side of the square model input in pixels.
        resize: `bicubic` | `area`.
    """

    size: int
    resize: str = "bicubic"

    def __post_init__(self) -> None:
        if self.resize not in RESIZE_MODES:
            raise ValueError(f"resize={self.resize!r} is not supported; use one of {list(RESIZE_MODES)}")

    def __call__(self, rgb: np.ndarray) -> torch.Tensor:
        """(H, W, 3) uint8 RGB -> (3, size, size) uint8 tensor (a copy; frames at the size pass unchanged)."""
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"image transform expects (H, W, 3) uint8 RGB, got {rgb.dtype} {rgb.shape}")
        if rgb.shape[:2] != (self.size, self.size):
            if self.resize == "bicubic":
                from PIL import Image

                rgb = np.asarray(Image.fromarray(rgb).resize((self.size, self.size), Image.BICUBIC))
            else:
                import cv2

                rgb = cv2.resize(rgb, (self.size, self.size), interpolation=cv2.INTER_AREA)
        return torch.from_numpy(np.array(rgb, dtype=np.uint8, copy=True)).permute(2, 0, 1).contiguous()


class OpenFlyProcessor(ProcessorMixin):
    """Images, prompts and action targets -> the model's inputs; generated action tokens -> action ids.

    Build it from a model config with `from_model_config` (what `OpenFlyAgent` does), or load it with
    `OpenFlyProcessor.from_pretrained(folder)` / `AutoProcessor.from_pretrained(release, trust_remote_code=True)`.

    Args:
        tokenizer: the text tokenizer (adds BOS itself or not; a pad token is required).
        image_size: side of the square model input (the vision config's `image_size`).
        resize: `bicubic` | `area` (the vision config's `resize`).
        prompt_template: text after the visual tokens, with an `{instruction}` placeholder.
        grounding_template: the text of a grounding sample, with an `{expression}` placeholder.
        lowercase: lowercase the instruction first.
        suffix_token_id: token appended after the prompt (None: none).
        max_length: the most text tokens (prompt + action targets) per sample; None: no limit.
        action_head: the action tokenizer's settings (`ActionTokenizer.to_dict()`).
        action_stats: the `action` norm stats the `openvla_bins` head un-normalises with (None: discrete).
        chat_template: unused (transformers' processor argument).
    """

    def __init__(
        self,
        tokenizer,
        image_size: int = 224,
        resize: str = "bicubic",
        prompt_template: str = DEFAULT_TEMPLATE,
        grounding_template: str = DEFAULT_GROUNDING_TEMPLATE,
        lowercase: bool = False,
        suffix_token_id: int | None = None,
        max_length: int | None = None,
        action_head: dict | None = None,
        action_stats: dict | None = None,
        chat_template=None,
    ) -> None:
        super().__init__(tokenizer, chat_template=chat_template)
        if tokenizer.pad_token_id is None:
            raise ValueError("the processor's tokenizer needs a pad token (OpenVLA adds <PAD> to Llama-2's)")
        if "{instruction}" not in prompt_template:
            raise ValueError(f"prompt_template={prompt_template!r} must contain {{instruction}}")
        self.image_size, self.resize = image_size, resize
        if "{expression}" not in grounding_template:
            raise ValueError(f"grounding_template={grounding_template!r} must contain {{expression}}")
        self.prompt_template, self.lowercase = prompt_template, lowercase
        self.grounding_template = grounding_template
        self.suffix_token_id, self.max_length = suffix_token_id, max_length
        self.action_head = dict(action_head or ActionTokenizer().to_dict())
        self.action_stats = action_stats
        # Derived objects (not saved: rebuilt from the settings above).
        self.image_transform = ImageTransform(image_size, resize)
        self.action_tokenizer = ActionTokenizer.from_dict(self.action_head, action_stats)

    @classmethod
    def from_model_config(
        cls, cfg: ModelConfig, tokenizer, norm_stats: dict | None = None
    ) -> OpenFlyProcessor:
        """The processor of a resolved model config (vocabulary and special ids filled, as the agent's).

        The text limit is the LLM context minus the visual tokens of a step with a full memory.
        """
        return cls(
            tokenizer,
            image_size=cfg.vision.image_size,
            resize=cfg.vision.resize,
            prompt_template=cfg.prompt.template,
            grounding_template=cfg.prompt.grounding_template,
            lowercase=cfg.prompt.lowercase,
            suffix_token_id=cfg.prompt.suffix_token_id,
            max_length=cfg.llm.max_length - cfg.visual_tokens_per_step(),
            action_head=make_action_tokenizer(cfg, norm_stats).to_dict(),
            action_stats=action_stats_of(cfg, norm_stats),
        )

    @classmethod
    def _load_tokenizer_from_pretrained(
        cls, sub_processor_type, pretrained_model_name_or_path, subfolder="", **kwargs
    ):
        """The tokenizer beside the processor config, read by its own tokenizer_config.json: the folder's config.json
        (an agent config, `auto_map` included) is not consulted, so loading runs no remote code."""
        from transformers import AutoTokenizer, PreTrainedConfig

        kwargs.pop("trust_remote_code", None)
        return AutoTokenizer.from_pretrained(
            pretrained_model_name_or_path, subfolder=subfolder, config=PreTrainedConfig(), **kwargs
        )

    # --- images -----------------------------------------------------------------------------------------------
    def image(self, rgb) -> torch.Tensor:
        """(H, W, 3) uint8 RGB -> (3, s, s) uint8 at the model's input size."""
        return self.image_transform(rgb)

    # --- text ---------------------------------------------------------------------------------------------------
    @property
    def pad_token_id(self) -> int:
        """Id that right-pads text batches."""
        return int(self.tokenizer.pad_token_id)

    def navigation_prompt(self, instruction: str) -> str:
        """The text after the visual tokens for a navigation `instruction` (the prompt template)."""
        text = instruction.strip()
        if self.lowercase:
            text = text.lower()
        return self.prompt_template.format(instruction=text)

    def grounding_prompt(self, expression: str) -> str:
        """The text after the visual tokens for a referring `expression` (grounding stage)."""
        text = expression.strip()
        if self.lowercase:
            text = text.lower()
        return self.grounding_template.format(expression=text)

    def encode(self, prompt: str, action: int | None = None) -> tuple[list[int], list[int]]:
        """`(input_ids, labels)` of one sample: `[BOS] prompt [suffix]`, then the action target's tokens.

        Args:
            prompt: the text after the visual tokens (e.g. `navigation_prompt(instruction)`).
            action: action id 0..9 to supervise, or None (inference; samples without an action target).

        Returns:
            Token ids and labels of the same length; labels are -100 except on the action tokens.
        """
        ids = [int(i) for i in self.tokenizer(prompt, add_special_tokens=True)["input_ids"]]
        bos = self.tokenizer.bos_token_id
        if bos is None:
            raise ValueError("the tokenizer has no BOS token: the model reads visual tokens after BOS")
        if not ids or ids[0] != bos:
            ids = [int(bos), *ids]
        if self.suffix_token_id is not None and ids[-1] != self.suffix_token_id:
            ids.append(int(self.suffix_token_id))  # OpenVLA's predict_action appends '▁' (29871)
        target = [] if action is None else [int(t) for t in self.action_tokenizer.action_to_token_ids(action)]
        if self.max_length is not None and len(ids) + len(target) > self.max_length:
            keep = self.max_length - len(target)
            if keep < 1:
                raise ValueError(
                    f"max_length={self.max_length} leaves no room for {len(target)} action tokens"
                )
            ids = ids[:keep]
        return ids + target, [IGNORE_INDEX] * len(ids) + target

    # --- batches ------------------------------------------------------------------------------------------------
    def __call__(
        self,
        text: str | list[str],
        images=None,
        actions: list[int | None] | None = None,
        **kwargs,
    ) -> BatchFeature:
        """A batch of prompts (+ frames, + action targets) -> model inputs.

        Args:
            text: prompt(s), the text after the visual tokens.
            images: one (H, W, 3) uint8 RGB frame per prompt (the current frame), or None.
            actions: one action id (or None) per prompt to supervise, or None for none at all.

        Returns:
            `input_ids`, `attention_mask` (B, L) long, right padded; `labels` (B, L) long when `actions` is
            given; `pixel_values` (B, 3, s, s) uint8 when `images` is given.
        """
        prompts = [text] if isinstance(text, str) else list(text)
        targets = [None] * len(prompts) if actions is None else list(actions)
        if len(targets) != len(prompts):
            raise ValueError(f"{len(prompts)} prompts but {len(targets)} actions")
        pairs = [self.encode(prompt, action) for prompt, action in zip(prompts, targets)]
        length = max(len(ids) for ids, _ in pairs)
        input_ids = torch.full((len(pairs), length), self.pad_token_id, dtype=torch.long)  # (B, L)
        labels = torch.full((len(pairs), length), IGNORE_INDEX, dtype=torch.long)  # (B, L)
        attention_mask = torch.zeros((len(pairs), length), dtype=torch.long)  # (B, L)
        for row, (ids, row_labels) in enumerate(pairs):
            input_ids[row, : len(ids)] = torch.tensor(ids)
            labels[row, : len(ids)] = torch.tensor(row_labels)
            attention_mask[row, : len(ids)] = 1
        data = {INPUT_IDS: input_ids, ATTENTION_MASK: attention_mask}
        if actions is not None:
            data[LABELS] = labels
        if images is not None:
            frames = (
                [images] if isinstance(images, torch.Tensor) or getattr(images, "ndim", 0) == 3 else images
            )
            if len(frames) != len(prompts):
                raise ValueError(f"{len(prompts)} prompts but {len(frames)} images")
            data[PIXEL_VALUES] = torch.stack([self.image(rgb) for rgb in frames])  # (B, 3, s, s)
        return BatchFeature(data)

    # --- actions ------------------------------------------------------------------------------------------------
    def decode_action(self, token_ids) -> int:
        """Action id 0..9 from generated token ids (discrete: 1 id; bins: the first 8)."""
        return self.action_tokenizer.token_ids_to_action(token_ids)

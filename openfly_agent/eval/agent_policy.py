"""The trained agent as a `Policy`: batched `select_action` with per-episode memory, plus its predictions.

`AgentPolicy` wraps any object with the agent's public inference API (`select_action(list[dict]) ->
list[int]`, `reset(episode_ids)`, optionally `last_step_info`), so the runner never touches model
internals. `load_agent` builds `OpenFlyAgent` from our checkpoint folder (a LoRA run's: its merged model when the
run wrote one, else the adapter on its base), a released OpenVLA / OpenFly-Agent folder (through the model's
`openvla_compat` path and `openvla_bins` head) or a Hub id.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

from openfly_agent import constants as C
from openfly_agent.eval.box_servo import OBS_TARGET_BOX
from openfly_agent.eval.config import AgentSettings, EvalInputError
from openfly_agent.eval.policy import OBS_EPISODE_ID
from openfly_agent.model.config import ModelConfig, openvla_compat_7b_config
from openfly_agent.model.language.tokenizer import load_tokenizer
from openfly_agent.model.persistence.checkpoint_path import check_navigation_stage, resolve_checkpoint_folder
from openfly_agent.model.persistence.lora_checkpoint import checkpoint_weights, load_lora_agent
from openfly_agent.utils.config import load_yaml_config

logger = logging.getLogger(__name__)


class AgentPolicy:
    """Adapter from the agent's inference API to the runner's `Policy` protocol.

    Args:
        agent: an `AgentSession` of an `OpenFlyAgent` (or anything with `select_action`, `reset`).
        name: the policy name in tables and folders.
        true_boxes: feed the simulator's true target box to the agent in place of its grounding head's
            (`agent_true_box`: the agent with perfect grounding; the runner adds `target_box` to observations).
    """

    needs_frames = True

    def __init__(self, agent, name: str = "agent", true_boxes: bool = False):
        if true_boxes and not hasattr(agent, "predict_step"):
            raise ValueError(f"{name}: the agent has no predict_step to take true boxes")
        self.agent = agent
        self.name = name
        self.needs_target_box = true_boxes
        self._details: dict[str, dict] = {}

    def reset(self, episode_ids: list[str]) -> None:
        self.agent.reset(list(episode_ids))
        for episode_id in episode_ids:
            self._details.pop(episode_id, None)

    def act(self, observations: list[dict]) -> list[int]:
        import torch

        inputs = [
            {key: obs[key] for key in (OBS_EPISODE_ID, C.OBS_INSTRUCTION, C.OBS_RGB, C.OBS_POSE)}
            for obs in observations
        ]
        with torch.inference_mode():
            if not hasattr(self.agent, "predict_step"):
                return [int(a) for a in self.agent.select_action(inputs)]
            if self.needs_target_box:
                results = self.agent.predict_step(inputs, [obs[OBS_TARGET_BOX] for obs in observations])
            else:
                results = self.agent.predict_step(inputs)
        for obs, result in zip(inputs, results):
            self._details[obs[OBS_EPISODE_ID]] = _details(result)
        return [int(result.action) for result in results]

    def step_details(self, episode_ids: list[str]) -> list[dict]:
        """The predicted landmark box (None when predicted invisible) and the keyframe sets in memory."""
        return [self._details.get(episode_id, {}) for episode_id in episode_ids]


def _details(result) -> dict:
    """`box`: (cx, cy, w, h) or None; `keyframes`: frame indices of the keyframe sets in the agent memory."""
    box = [float(v) for v in result.box] if getattr(result, "box_visible", False) else None
    sets = getattr(result, "memory_sets", None)  # one tuple of frame indices per keyframe set, oldest first
    if sets is None:
        return {"box": box, "keyframes": None}
    return {"box": box, "keyframes": [[int(i) for i in frames] for frames in sets]}


def resolve_device(device: str, info_device=None) -> str:
    """`auto` -> the launcher's device for this process (accelerate), else cuda when present, else cpu."""
    import torch

    if device != "auto":
        return device
    if info_device is not None:
        return str(info_device)
    return "cuda" if torch.cuda.is_available() else "cpu"


def resolve_dtype(dtype: str, device: str):
    """`auto` -> bfloat16 on CUDA, float32 elsewhere."""
    import torch

    if dtype == "auto":
        return torch.bfloat16 if device.startswith("cuda") else torch.float32
    return getattr(torch, dtype)


def checkpoint_folder(checkpoint: str) -> Path:
    """The checkpoint's HF folder: a folder with config.json as is; a training run (`<run>`,
    `<run>/checkpoints` or the `last` pointer file) resolved to its newest checkpoint; otherwise a Hub id
    resolved through the local Hub cache (or a download when online). A grounding-stage checkpoint is refused
    (EvalInputError naming the navigation stage: it has no trained action head)."""
    try:
        folder = resolve_checkpoint_folder(checkpoint)
    except FileNotFoundError as err:
        raise FileNotFoundError(f"--checkpoint {checkpoint!r}: {err}") from err
    if folder is not None:
        try:
            check_navigation_stage(folder)
        except ValueError as err:
            raise EvalInputError(f"--checkpoint {checkpoint!r}: {err}") from err
        return folder
    if checkpoint.startswith((".", "/")) or checkpoint.count("/") != 1:
        raise FileNotFoundError(
            f"--checkpoint {checkpoint!r}: no config.json there (nor a training run with checkpoints/last, "
            "nor a Hub id 'owner/name')"
        )
    from huggingface_hub import snapshot_download

    return Path(snapshot_download(repo_id=checkpoint))


def checkpoint_fingerprint(checkpoint: str) -> dict:
    """What identifies the weights behind `checkpoint`: the resolved folder and its weight files' sizes and
    modification times (a training run folder keeps its name while its newest checkpoint changes)."""
    folder = checkpoint_folder(checkpoint)
    if checkpoint_kind(folder) == C.MODEL_TYPE:
        folder = checkpoint_weights(folder).folder  # a LoRA run: its merged model, or the adapter checkpoint
    files = sorted([*folder.glob("*.safetensors"), *folder.glob(f"{C.ADAPTER_DIR_NAME}/*.safetensors")])
    return {
        "folder": str(folder.resolve()),
        "weights": {str(f.relative_to(folder)): [f.stat().st_size, f.stat().st_mtime_ns] for f in files},
    }


def checkpoint_kind(folder: Path) -> str:
    """`openfly_agent` (ours) or `openvla` (a released OpenVLA / OpenFly-Agent folder), from config.json."""
    config = folder / C.CONFIG_NAME
    if not config.is_file():
        raise FileNotFoundError(f"{config} not found: a checkpoint folder holds config.json and safetensors")
    model_type = json.loads(config.read_text()).get("model_type")
    if model_type == C.MODEL_TYPE:
        return C.MODEL_TYPE
    if model_type == "openvla":
        return "openvla"
    raise EvalInputError(f"{config}: model_type {model_type!r} is neither {C.MODEL_TYPE!r} nor 'openvla'")


def _released_model_config(settings: AgentSettings):
    cfg = (
        load_yaml_config(ModelConfig, settings.model_config)
        if settings.model_config
        else openvla_compat_7b_config()
    )
    head = dataclasses.replace(
        cfg.action_head,
        unnorm_key=settings.unnorm_key or cfg.action_head.unnorm_key,
        decode_rule=settings.decode_rule or cfg.action_head.decode_rule,
    )
    return dataclasses.replace(cfg, action_head=head)


def load_agent(checkpoint: str, settings: AgentSettings, device: str):
    """Load the agent of `checkpoint` on `device`, in eval mode, with the decoding settings applied.

    Our folders load with `OpenFlyAgent.from_pretrained`, then take the decoding settings through their config
    (`set_action_decoding`: the action tokenizer, `config.action_tokenizer` and the processor all follow);
    OpenVLA-format folders (the released OpenFly-Agent) through `agent_from_openvla_checkpoint` with the
    `openvla_compat` model config (`settings.model_config`, default the 7B preset) and its `openvla_bins` head.
    A LoRA checkpoint (adapter only) loads as `checkpoint_weights` says, logged: the run's merged model when it
    wrote one, else the adapter on its base (the run's `init.checkpoint`).
    """
    from openfly_agent.model.agent import OpenFlyAgent  # lazy: torch + transformers
    from openfly_agent.model.persistence.openvla_loader import agent_from_openvla_checkpoint  # lazy: torch

    folder = checkpoint_folder(checkpoint)
    dtype = resolve_dtype(settings.dtype, device)
    if checkpoint_kind(folder) == "openvla":
        agent, report = agent_from_openvla_checkpoint(
            folder,
            _released_model_config(settings),
            tokenizer=load_tokenizer(folder),
            device=device,
            dtype=dtype,
        )
        logger.info("released checkpoint %s: %s", folder, report.summary())
        return agent.eval()
    weights = checkpoint_weights(folder)
    if weights.base is None:
        agent = OpenFlyAgent.from_pretrained(str(weights.folder), dtype=dtype)
    else:
        agent = load_lora_agent(weights.folder, weights.base).to(dtype)
    agent = agent.to(device).eval()
    agent.set_action_decoding(decode_rule=settings.decode_rule, unnorm_key=settings.unnorm_key)
    logger.info("evaluating %s on %s (%s)", weights.description, device, dtype)
    return agent

"""A synthetic OpenVLA-layout checkpoint folder: what `--init.checkpoint` of the 7B train configs reads.

    python bench/synthetic_openvla.py --size reduced --out /tmp/openvla-reduced   # seconds, a few MB
    python bench/synthetic_openvla.py --size full --out /tmp/openvla-7b           # about 15 GB (bf16)

The folder is laid out as the released openvla/openvla-7b and IPEC-COMMUNITY/openfly-agent-7b ones are: the
weights in bf16 safetensors shards (`model-0000i-of-0000N.safetensors`, `--shards`) with
`model.safetensors.index.json`, a `config.json` with `model_type: openvla` and `norm_stats`, and the tokenizer
files (a byte-level BPE of at most 1,024 tokens trained here, with a pad token; the released folders hold
Llama-2's). Key names and shapes are the real ones of the model config: every tensor the agent loads
(`to_openvla_state_dict`) plus the ViT parts it prunes (the last blocks, the final norms, SigLIP's pooling
head), so `--size full` holds the released openvla-7b's 7,541,237,184 parameters. Values are random: matrices
N(0, 0.02), norm weights 1, LayerScale 1e-5, biases 0 (the rule of model/persistence/random_init.py).

`--size full` is configs/model/openfly-7b.yaml as shipped; `--size reduced` is the same model with
configs/model/reduced-width.yaml laid over it (`REDUCED_WIDTH`), the width the CPU tests train the 7B configs at:
the same module classes (timm DINOv2-with-registers and SigLIP ViTs, a Llama decoder, the fused projector) at
small width. Train a 7B config at that width by adding `--model=configs/model/reduced-width.yaml` to train.py's
arguments (`reduced_width_args()`). Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
import yaml

from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.config import ModelConfig
from openfly_agent.model.language.tokenizer import train_bpe_tokenizer
from openfly_agent.model.persistence.openvla_loader import (
    VISION_PREFIXES,
    agent_to_openvla_key,
    to_openvla_state_dict,
)
from openfly_agent.model.persistence.random_init import INIT_STD, LAYER_SCALE_INIT
from openfly_agent.model.vision.backbone import build_featurizers
from openfly_agent.utils.config import flat_settings, load_yaml_config

REPO_ROOT = Path(__file__).resolve().parents[1]
MODEL_CONFIG = REPO_ROOT / "configs" / "model" / "openfly-7b.yaml"
SIZES = ("full", "reduced")
# The 7B model at reduced width (the file says what it changes): laid over a train config's model section with
# `--model=configs/model/reduced-width.yaml`, the one copy of these settings.
REDUCED_WIDTH = REPO_ROOT / "configs" / "model" / "reduced-width.yaml"
TOKENIZER_VOCAB = 1024
NORM_STATS = {  # one profile in OpenVLA's layout (`openvla_bins` heads un-normalise with it)
    "vlnv1": {"action": {"q01": [0.0] * 8, "q99": [1.0, 9.0, 15.0, 15.0, 2.0, 2.0, 5.0, 5.0]}}
}
CORPUS = [
    f"{verb} the {colour} {thing} {where}"
    for verb in ("fly to", "turn left at", "turn right at", "ascend above", "descend next to", "stop near")
    for colour in ("red", "white", "blue", "grey", "green", "yellow")
    for thing in ("tower", "house", "dome", "skyscraper", "billboard", "park", "spire", "bridge")
    for where in ("ahead.", "on the left.", "after the crossing.", "then go straight.")
]


def reduced_width_args() -> list[str]:
    """train.py's argument that shrinks a 7B train config to `REDUCED_WIDTH`."""
    return [f"--model={REDUCED_WIDTH.relative_to(REPO_ROOT).as_posix()}"]


def model_config(size: str) -> ModelConfig:
    """configs/model/openfly-7b.yaml at `size` ("full" as shipped, or "reduced": `REDUCED_WIDTH` laid over it)."""
    if size not in SIZES:
        raise ValueError(f"size={size!r}: choose one of {SIZES}")
    reduced = flat_settings(yaml.safe_load(REDUCED_WIDTH.read_text())) if size == "reduced" else {}
    return load_yaml_config(ModelConfig, MODEL_CONFIG, [f"--{key}={value}" for key, value in reduced.items()])


def openvla_shapes(cfg: ModelConfig, tokenizer) -> dict[str, torch.Size]:
    """Every key of an OpenVLA checkpoint of `cfg` (its layout: LayerScale `scale_factor`) -> shape, built on the
    meta device (no memory): the agent's loadable tensors, then the full ViTs' keys the agent prunes."""
    with torch.device("meta"):
        agent = OpenFlyAgent.from_model_config(cfg, tokenizer=tokenizer)
        full_vits = build_featurizers(cfg.vision, prune=False)
    shapes = {key: tensor.shape for key, tensor in to_openvla_state_dict(agent).items()}
    for prefix, vit in zip(VISION_PREFIXES, full_vits):
        for key, tensor in vit.state_dict().items():
            shapes.setdefault(agent_to_openvla_key(prefix + key), tensor.shape)
    return shapes


def random_tensor(key: str, shape: torch.Size, generator: torch.Generator) -> torch.Tensor:
    """A bf16 CPU tensor for `key`: matrices (and tokens) N(0, 0.02), norm weights 1, LayerScale 1e-5, biases 0.

    The normal values are drawn on the generator's device (a GPU draws 7.5 B of them in well under a second; one
    CPU thread of a GPU machine took over 150 s for a third of them), so they depend on that device."""
    if len(shape) >= 2:
        values = torch.empty(shape, dtype=torch.bfloat16, device=generator.device)
        return values.normal_(0.0, INIT_STD, generator=generator).cpu()
    value = LAYER_SCALE_INIT if key.endswith("scale_factor") else 1.0 if key.endswith("weight") else 0.0
    return torch.full(shape, value, dtype=torch.bfloat16)


def shard_keys(shapes: dict[str, torch.Size], shards: int) -> list[list[str]]:
    """The keys in `shards` consecutive groups of about equal bytes (each non-empty)."""
    keys = list(shapes)
    sizes = [shapes[k].numel() for k in keys]
    total, groups, current, done = sum(sizes), [], [], 0
    for key, size in zip(keys, sizes):
        current.append(key)
        done += size
        if done >= total * (len(groups) + 1) / shards and len(groups) < shards - 1:
            groups.append(current)
            current = []
    return [*groups, current] if current else groups


def write_synthetic_openvla(
    out: str | Path, size: str, shards: int = 3, seed: int = 0, device: str = "cpu"
) -> dict:
    """Write the folder (see the module docstring); returns a summary (parameters, tensors, shards, bytes).

    `device` draws the random values (`cuda` for the full size on a GPU machine; the same seed gives other
    values on another device)."""
    from safetensors.torch import save_file

    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    tokenizer = train_bpe_tokenizer(CORPUS, TOKENIZER_VOCAB, out_dir=folder)
    shapes = openvla_shapes(model_config(size), tokenizer)
    groups = shard_keys(shapes, shards)
    generator = torch.Generator(device=device).manual_seed(seed)
    weight_map, total_bytes = {}, 0
    for index, keys in enumerate(groups, start=1):
        name = f"model-{index:05d}-of-{len(groups):05d}.safetensors"
        tensors = {key: random_tensor(key, shapes[key], generator) for key in keys}
        total_bytes += sum(t.numel() * t.element_size() for t in tensors.values())
        save_file(tensors, str(folder / name), metadata={"format": "pt"})
        weight_map.update(dict.fromkeys(keys, name))
        del tensors
    index = {"metadata": {"total_size": total_bytes}, "weight_map": weight_map}
    (folder / "model.safetensors.index.json").write_text(json.dumps(index, indent=2) + "\n")
    config = {
        "model_type": "openvla",
        "architectures": ["OpenVLAForActionPrediction"],
        "torch_dtype": "bfloat16",
        "norm_stats": NORM_STATS,
    }
    (folder / "config.json").write_text(json.dumps(config, indent=2) + "\n")
    return {
        "folder": str(folder),
        "size": size,
        "device": device,
        "parameters": sum(shape.numel() for shape in shapes.values()),
        "tensors": len(shapes),
        "shards": len(groups),
        "bytes": total_bytes,
        "tokenizer_tokens": len(tokenizer),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--out", required=True, help="the folder to write (created; files in it are replaced)"
    )
    parser.add_argument(
        "--size", choices=SIZES, default="reduced", help="full: 7B as shipped; reduced: small width"
    )
    parser.add_argument("--shards", type=int, default=3, help="safetensors shards (the released folders: 3)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random values")
    parser.add_argument(
        "--device", default=None, help="where the random values are drawn (default: cuda when there is one)"
    )
    args = parser.parse_args(argv)
    device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    start = time.perf_counter()
    summary = write_synthetic_openvla(args.out, args.size, args.shards, args.seed, device)
    print(json.dumps({**summary, "seconds": round(time.perf_counter() - start, 1)}))


if __name__ == "__main__":
    main()

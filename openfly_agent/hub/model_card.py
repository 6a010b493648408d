"""Model card: YAML metadata (licence, tags, base model, `model-index` from eval results) + a Jinja body."""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import yaml

from openfly_agent.hub.config import CardConfig
from openfly_agent.hub.results import AGENT_POLICY, EvalResults, ResultRow
from openfly_agent.model.config import (
    ENCODING_OPENVLA_HISTORY,
    LLM_LLAMA2_7B,
    VISION_DINOSIGLIP_224,
    VISION_TINY,
    VISION_TINY_CNN,
    ModelConfig,
)
from openfly_agent.rollout.stats import format_interval

# Always present; the Hub adds `custom_code` itself for repos with `auto_map`, we state it explicitly.
FIXED_TAGS = (
    "openfly",
    "openfly-agent",
    "vision-language-navigation",
    "aerial-vln",
    "uav",
    "vla",
    "custom_code",
)
TASK_TYPE = "robotics"
TASK_NAME = "Aerial vision-language navigation"
# metric key -> (model-index `type`, pretty name with unit)
METRIC_IDS = {
    "NE": ("ne", "NE (m)"),
    "SR": ("sr", "SR (%)"),
    "OSR": ("osr", "OSR (%)"),
    "SPL": ("spl", "SPL (%)"),
}
PROFILE_SUMMARIES = {
    "openfly": (
        "parity with the official OpenFly evaluation: 3-D distance to the goal, success within 20 m, no "
        "STOP needed, SPL = straight-line start-goal distance / travelled length without clamp, no "
        "collision check."
    ),
    "standard": (
        "VLN-CE style: the agent must STOP within 20 m, a collision ends the episode as a failure, "
        "SPL = S * L / max(P, L) with L the reference path length and P the travelled length."
    ),
}
TEMPLATE_NAME = "model_card.md.j2"
# What each policy of an eval run is, for the reference rows beside the agent's (eval/config.py POLICY_NAMES).
POLICY_DESCRIPTIONS = {
    AGENT_POLICY: "this model",
    "agent_true_box": "this model fed the simulator's true target box instead of its grounding head's (perfect "
    "grounding)",
    "box_servo": "a reflex policy that flies toward the simulator's true target box (no learning)",
    "random": "uniformly random actions",
    "stop": "STOP at the first step",
    "forward": "always fly forward",
    "oracle": "replays the reference actions of each episode",
}


@dataclass
class ModelFacts:
    """What the card body says about the released weights (filled by the release builder).

    Attributes:
        architecture: the network, from the checkpoint's model config (`describe_architecture`).
        training_progress: steps trained vs configured, from trainer_state.json and train_config.json
            (`describe_training_progress`); None when the checkpoint records neither.
        lora_summary: what the LoRA fine-tune was (`describe_lora`); None for weights not trained as LoRA.
    """

    package_version: str
    num_parameters: str
    action_head: str
    architecture: str
    weights_summary: str
    release_form: str
    files: dict[str, str] = field(default_factory=dict)
    train_summary: str | None = None
    training_progress: str | None = None
    adapter_release: bool = False
    lora_summary: str | None = None


def describe_architecture(cfg: ModelConfig) -> str:
    """One sentence of the network's parts as its config builds them (vision backbone, LLM, heads, memory)."""
    vision = cfg.vision
    grid = f"{vision.grid_side} x {vision.grid_side} tokens per frame"
    backbones = {
        VISION_DINOSIGLIP_224: f"the fused DINOv2 + SigLIP vision encoder (`{vision.type}`, {vision.image_size} "
        f"px, {grid})",
        VISION_TINY: f"two small ViTs of the DINOv2 + SigLIP structure (`{vision.type}`, {vision.image_size} px, "
        f"{grid})",
        VISION_TINY_CNN: f"a small ResNet vision encoder (`{vision.type}`, {vision.image_size} px, {grid})",
    }
    llm = cfg.llm
    language_model = (
        "the Llama 2 7B causal LM"
        if llm.type == LLM_LLAMA2_7B
        else f"a {llm.num_layers}-layer Llama-architecture causal LM of width {llm.hidden_size} (`{llm.type}`)"
    )
    parts = [backbones[vision.type], "an MLP projector", language_model]
    parts.append("a landmark grounding head" if cfg.grounding.has_head else "no grounding head")
    capacity = cfg.memory.capacity
    if capacity:
        merging = "with visual token merging" if cfg.merging.enabled else "without token merging"
        parts.append(f"keyframe selection {merging} into a FIFO memory of {capacity} keyframe set(s)")
    else:
        parts.append("no history memory (the current frame only)")
    text = ", ".join(parts[:-1]) + f", and {parts[-1]}"
    if cfg.memory.encoding.type == ENCODING_OPENVLA_HISTORY:
        text += f"; it runs the released OpenVLA-format forward (`{ENCODING_OPENVLA_HISTORY}` memory)"
    return text


def describe_training_progress(
    train_config: dict[str, Any] | None, trainer_state: dict[str, Any] | None
) -> str | None:
    """`Trained for 1,682 of the 6,000 configured optimizer steps ...` (None when neither file was found)."""
    if not trainer_state and not train_config:
        return None
    config = train_config or {}
    planned = config.get("steps")
    if not trainer_state:
        return (
            "The checkpoint records no trainer state (trainer_state.json), so the optimizer steps it was trained "
            "for are unknown" + (f"; {planned:,} were configured." if planned else ".")
        )
    done = int(trainer_state.get("step", 0))
    if planned and done < planned:
        return (
            f"Trained for {done:,} of the {planned:,} configured optimizer steps: the run ended early (its time "
            "limit, a stop signal or a crash; the run's logs say which)."
        )
    if planned:
        return f"Trained for {done:,} optimizer steps, as configured."
    epochs = config.get("epochs")
    return f"Trained for {done:,} optimizer steps" + (f" ({epochs} epochs configured)." if epochs else ".")


def describe_lora(
    adapter_config: dict[str, Any],
    base: str | None,
    train_config: dict[str, Any] | None,
    trainer_state: dict[str, Any] | None,
    merged: bool,
) -> str:
    """`These weights are a LoRA fine-tune of ... (rank 32, alpha 16 on q_proj, v_proj ...), trained on ... for N
    optimizer steps; ...`: the adapter from peft's adapter_config.json, the rest from the run's records."""
    modules = adapter_config.get("target_modules") or []  # peft's resolved names: one per layer and module
    modules = [modules] if isinstance(modules, str) else sorted({name.rsplit(".", 1)[-1] for name in modules})
    data = ((train_config or {}).get("data") or {}).get("root")
    steps = (trainer_state or {}).get("step")
    text = (
        f"These weights are a **LoRA fine-tune** of {f'`{base}`' if base else 'randomly initialised weights'}: "
        f"adapters of rank {adapter_config.get('r')} and alpha {adapter_config.get('lora_alpha')} on the "
        f"language model's {', '.join(f'`{m}`' for m in modules) or 'unrecorded'} layers, the projector and "
        f"grounding head trained in full, trained on {f'`{data}`' if data else 'data the release does not record'}"
        f" for {f'{int(steps):,}' if steps is not None else 'an unrecorded number of'} optimizer steps. "
    )
    if merged:
        return text + "This release holds the adapter merged into those base weights (full weights, no peft)."
    return text + "This release holds the adapter alone, to load on those base weights (see Usage)."


# Dotted keys of train_config.json (training.config.TrainConfig) shown in the card's training table.
TRAIN_SUMMARY_KEYS = (
    "init.checkpoint",
    "data.root",
    "data.history.mode",
    "freeze_stage",
    "steps",
    "epochs",
    "batch.global_batch_size",
    "optim.lr",
    "optim.schedule",
    "precision",
    "seed",
)


_MISSING = object()


def summarize_train_config(train_config: dict[str, Any]) -> str | None:
    """A Markdown table of the main training settings (TRAIN_SUMMARY_KEYS found in `train_config`)."""
    rows = []
    for key in TRAIN_SUMMARY_KEYS:
        node: Any = train_config
        for part in key.split("."):
            node = node.get(part, _MISSING) if isinstance(node, dict) else _MISSING
        if node is not _MISSING and node is not None:
            rows.append(f"| `{key}` | `{node}` |")
    if not rows:
        return None
    return "\n".join(["| setting (as configured) | value |", "|---|---|", *rows])


def build_model_index(model_name: str, rows: list[ResultRow], card: CardConfig) -> list[dict[str, Any]]:
    """The card's `model-index`: one result block per (split, metric profile), metrics NE / SR / OSR / SPL.

    Each block names its profile in `task.name`, and every metric carries it as `config` (the Hub's "metric
    configuration") so the profile survives tools that regroup blocks by dataset and split.
    """
    results = []
    for row in rows:
        metrics = [
            {
                "type": METRIC_IDS[key][0],
                "name": METRIC_IDS[key][1],
                "value": row.metrics[key],
                "config": row.profile,
            }
            for key in METRIC_IDS
        ]
        results.append(
            {
                "task": {"type": TASK_TYPE, "name": f"{TASK_NAME} ({row.profile} metric profile)"},
                "dataset": {
                    "type": card.eval_dataset,
                    "name": f"{card.eval_dataset_name} ({row.split})",
                    "split": row.split,
                },
                "metrics": metrics,
            }
        )
    return [{"name": model_name, "results": results}]


def build_metadata(
    card: CardConfig, model_name: str, rows: list[ResultRow] | None, adapter: bool = False
) -> dict[str, Any]:
    """The YAML front matter as a dict, keys in the order the Hub documents them."""
    meta: dict[str, Any] = {"license": card.license}
    if card.license == "other":
        meta["license_name"] = card.license_name
        meta["license_link"] = card.license_link
    meta["library_name"] = "transformers"
    meta["pipeline_tag"] = card.pipeline_tag
    meta["language"] = list(card.language)
    extra = ["lora"] if adapter else []
    meta["tags"] = list(dict.fromkeys([*FIXED_TAGS, *extra, *card.tags]))
    if card.datasets:
        meta["datasets"] = list(card.datasets)
    if card.base_model:
        meta["base_model"] = card.base_model
        if adapter:
            meta["base_model_relation"] = "adapter"
    if rows:
        meta["model-index"] = build_model_index(model_name, rows, card)
    return meta


def describe_profile(name: str, settings: dict[str, Any] | None) -> str:
    """One line per metric profile: what it is for, plus the exact settings eval.py recorded."""
    text = PROFILE_SUMMARIES.get(name, "custom metric profile.")
    if settings:
        shown = ", ".join(f"{key}={value}" for key, value in settings.items() if key != "name")
        text += f" Settings used: {shown}."
    return text


# Keys of eval.py's results `meta` that change the numbers, shown next to them.
RUN_KEYS = ("sim", "max_steps", "seed", "unnorm_key")


def describe_run(meta: dict[str, Any]) -> str:
    """`sim=embedded, max_steps=100, ...` from the results' run settings (empty when none were recorded)."""
    return ", ".join(f"`{key}={meta[key]}`" for key in RUN_KEYS if meta.get(key) is not None)


def table_rows(results: EvalResults, baselines: list[EvalResults]) -> list[dict[str, Any]]:
    """The card's results table: per split and profile, the agent's row then each baseline's."""
    by_key = [{(row.split, row.profile): row for row in other.rows} for other in baselines]
    rows = []
    for row in results.rows:
        for policy, policy_row in [(results.policy, row)] + [
            (other.policy, rows_of[(row.split, row.profile)])
            for other, rows_of in zip(baselines, by_key)
            if (row.split, row.profile) in rows_of
        ]:
            rows.append(
                {
                    "policy": policy,
                    "row": policy_row,
                    "episodes": _episodes_cell(policy_row),
                    "successes": _successes_cell(policy_row),
                    "cells": {
                        name: format_interval(value, policy_row.intervals.get(name))
                        for name, value in policy_row.metrics.items()
                    },
                }
            )
    return rows


def _successes_cell(row: ResultRow) -> str:
    """`4 of 17`: the episodes that succeeded under the row's profile."""
    if row.successes is None or row.num_episodes is None:
        return "-"
    return f"{row.successes} of {row.num_episodes}"


def _episodes_cell(row: ResultRow) -> str:
    if row.num_episodes is None:
        return "-"
    if row.split_episodes is not None:
        return f"{row.num_episodes} of {row.split_episodes}"
    return str(row.num_episodes)


def describe_subsample(results: EvalResults) -> str | None:
    """`Evaluated on 40 of 520 test_seen episodes and ...` when `--max_episodes` cut the splits (else None)."""
    if not results.subsampled:
        return None
    parts = {
        row.split: f"{row.num_episodes} of {row.split_episodes} {row.split} episodes"
        for row in results.rows
        if row.split_episodes is not None
    }
    flag = results.meta.get("max_episodes")
    how = f"`--max_episodes {flag}`, " if flag else ""
    return (
        f"Evaluated on a subsample: {' and '.join(parts.values())} ({how}evenly spaced over the sorted episode "
        "ids); the full splits may give other numbers."
    )


def install_instructions(version: str, code_url: str | None) -> str:
    """How to install the package the release needs: from a clone (nothing publishes it on PyPI)."""
    if code_url:
        return (
            f"```bash\ngit clone {code_url} openfly-agent\n"
            f"pip install -e ./openfly-agent  # this release was built with version {version}\n```"
        )
    return (
        f"Install the `openfly-agent` package from a clone of its source repository (`pip install -e <clone>`; "
        f"version {version} built this release). It is not published on PyPI."
    )


def render_model_card(
    card: CardConfig,
    repo_id: str,
    results: EvalResults | None,
    facts: ModelFacts,
    baselines: list[EvalResults] | None = None,
) -> str:
    """Render README.md: YAML front matter (yaml.safe_dump, so it always parses) + the Jinja body.

    `baselines` (the other policies of the same eval run) appear beside the agent in the results table only;
    the `model-index` holds the agent's numbers.
    """
    import jinja2

    model_name = repo_id.split("/", 1)[1]
    rows = results.rows if results else []
    baselines = list(baselines or [])
    meta = build_metadata(card, model_name, rows, adapter=facts.adapter_release)
    profiles = {row.profile: describe_profile(row.profile, results.profiles.get(row.profile)) for row in rows}
    template_text = resources.files("openfly_agent.hub").joinpath("templates", TEMPLATE_NAME).read_text()
    env = jinja2.Environment(undefined=jinja2.StrictUndefined, keep_trailing_newline=True, autoescape=False)
    body = env.from_string(template_text).render(
        model_name=model_name,
        repo_id=repo_id,
        base_model=card.base_model,
        eval_dataset=card.eval_dataset,
        eval_dataset_name=card.eval_dataset_name,
        results=table_rows(results, baselines) if results else [],
        references={other.policy: POLICY_DESCRIPTIONS.get(other.policy, "") for other in baselines},
        subsample_note=describe_subsample(results) if results else None,
        profile_definitions=profiles,
        run_settings=describe_run(results.meta if results else {}),
        install=install_instructions(facts.package_version, card.code_url),
        **vars(facts),
    )
    front = yaml.safe_dump(meta, sort_keys=False, allow_unicode=True, width=1000)
    text = f"---\n{front}---\n\n{body}"
    validate_model_card(text)
    return text


def split_front_matter(text: str) -> tuple[dict[str, Any], str]:
    """Split a card into (YAML metadata, Markdown body); ValueError when the front matter is malformed."""
    if not text.startswith("---\n"):
        raise ValueError("card has no YAML front matter: it must start with a '---' line")
    end = text.find("\n---\n", 4)
    if end < 0:
        raise ValueError("card front matter is not closed by a '---' line")
    meta = yaml.safe_load(text[4 : end + 1])
    if not isinstance(meta, dict):
        raise ValueError(f"card front matter is not a mapping: {type(meta).__name__}")
    return meta, text[end + 5 :]


def validate_model_card(text: str) -> None:
    """Parse `text` the way the Hub client does (huggingface_hub.ModelCard, strict) and fail on any error."""
    from huggingface_hub import ModelCard

    meta, _ = split_front_matter(text)
    card = ModelCard(text, ignore_metadata_errors=False)
    if "model-index" in meta and not card.data.eval_results:
        raise ValueError("card model-index parsed to no eval results")

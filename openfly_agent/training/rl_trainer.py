"""The RL stage (`train.py --stage=rl`): GRPO fine-tuning of a navigation checkpoint in the simulator.

One update (`rl` section, training/config.py):
1. draw `episodes_per_update` train episodes and fly `group_size` rollouts of each with the policy sampling its
   action (training/rl_rollouts.py: the rollout layer over a `VectorSimulator`, so a bridge serves as well as
   the embedded city);
2. reward each rollout with the simulator's own success under `rl.profile` (rollout/metrics.py), plus the shaping
   terms that are on; group-relative advantages (training/rl_loss.py); the steps of a group whose rewards are
   all equal carry no signal and are left out;
3. replay every kept step through the agent's training forward (its frame, memory, instruction, predicted box
   and taken action as a batch: the same network path as the rollout, in eval mode, so no box jitter and the
   BatchNorm statistics of the rollout) for the log-probs of the taken actions under the update's starting
   policy and under the reference (the `init.checkpoint` policy, frozen: training/rl_reference.py, a copy of the
   agent, or with LoRA the model itself with its adapters off);
4. `epochs` x `minibatches` AdamW steps on the clipped policy loss + `kl_coef` x k3 KL + `grounding_weight` x
   the grounding loss (steps where the simulator reports boxes); the lr schedule steps once per update.

Every draw of an update comes from seeds derived from (`seed`, update index), so a run resumed from a checkpoint
flies and trains exactly as the uninterrupted run does; the optimizer, schedule and weights come back from the
checkpoint as in the other stages (training/saving.py). A LoRA run also writes `<output_dir>/merged` at the end
(`lora.merge_at_end`), as the navigation stage does.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from openfly_agent import constants as C
from openfly_agent.data.collator import NavigationCollator
from openfly_agent.data.generation_settings import read_generation_settings
from openfly_agent.model.agent import OpenFlyAgent
from openfly_agent.model.config import HEAD_DISCRETE
from openfly_agent.model.persistence.checkpoint_path import resolve_checkpoint_folder
from openfly_agent.model.persistence.lora_checkpoint import (
    has_full_weights,
    is_lora_checkpoint,
    merged_model_of,
)
from openfly_agent.rollout.profiles import MetricProfile, get_profile
from openfly_agent.sim.embedded import EmbeddedSimConfig
from openfly_agent.sim.embedded_scenes import city_config, is_embedded_scene
from openfly_agent.sim.vector import VectorSimulator
from openfly_agent.training.accelerator import closing_trackers, flat_config, make_accelerator
from openfly_agent.training.builder import Splits, load_splits, prepare_agent
from openfly_agent.training.checkpoint import CheckpointManager
from openfly_agent.training.config import TrainConfig
from openfly_agent.training.export import export_merged_lora
from openfly_agent.training.metrics import RunningMeans
from openfly_agent.training.optim import make_optimizer, make_scheduler
from openfly_agent.training.preflight import (
    PreflightError,
    check_dataset_root,
    check_output_dir,
    resolve_val_split,
)
from openfly_agent.training.resume_settings import record_run_settings, resume_changes
from openfly_agent.training.rl_loss import action_log_probs, group_advantages, rl_loss
from openfly_agent.training.rl_reference import describe_reference, make_reference
from openfly_agent.training.rl_rollouts import Rollout, collect_groups, step_sample
from openfly_agent.training.saving import register_state_hooks, restore_checkpoint, save_checkpoint
from openfly_agent.training.state import TrainerState
from openfly_agent.training.stops import SIGNAL, STOP_AFTER_STEPS_ENV, StopFlags, forced_stop_step
from openfly_agent.training.trackers import start_trackers
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)


@dataclass
class RLRun:
    """What the RL stage ends with: counters, the last checkpoint, whether it stopped early, the agent."""

    state: TrainerState
    checkpoint: Path | None
    stopped_early: bool
    agent: OpenFlyAgent
    is_main_process: bool


def update_seeds(seed: int, update: int) -> tuple[np.random.Generator, torch.Generator]:
    """The update's two random streams, from (`seed`, `update`) alone: episodes and minibatch order (numpy), and
    the rollouts' action samples (torch)."""
    rng = np.random.default_rng([seed, update])
    return rng, torch.Generator().manual_seed(int(rng.integers(2**62)))


def check_rl_run(
    cfg: TrainConfig, splits: Splits, num_processes: int, embedded: bool = True
) -> MetricProfile:
    """What the RL stage needs beyond the other stages' checks; returns the reward's metric profile.
    `embedded`: the run flies the embedded city (its train scenes must be embedded ones)."""
    if num_processes != 1:
        raise PreflightError(f"stage=rl runs in one process (this launch has {num_processes})")
    if cfg.model.action_head.type != HEAD_DISCRETE:
        raise PreflightError(f"stage=rl samples actions from the {HEAD_DISCRETE} action head only")
    try:
        profile = get_profile(cfg.rl.profile)
    except (KeyError, ValueError) as err:
        raise PreflightError(f"rl.profile: {err}") from err
    train = splits.episodes[C.SPLIT_TRAIN]
    if len(train) < cfg.rl.episodes_per_update:
        raise PreflightError(
            f"rl.episodes_per_update={cfg.rl.episodes_per_update} but {C.SPLIT_TRAIN} has {len(train)} episodes"
        )
    foreign = sorted({e.scene_id for e in train if not is_embedded_scene(e.scene_id)})
    if foreign and embedded:
        raise PreflightError(
            f"stage=rl flies the embedded city; {C.SPLIT_TRAIN} has other scenes ({', '.join(foreign[:3])})"
        )
    check_full_weights(cfg.init.checkpoint)
    return profile


def check_full_weights(init_checkpoint: str) -> None:
    """The RL stage starts from full weights (its LoRA reference is the model with fresh adapters off,
    training/rl_reference.py): a LoRA run's adapter-only checkpoint is refused, naming the run's merged model."""
    try:
        folder = resolve_checkpoint_folder(init_checkpoint)
    except FileNotFoundError:
        return  # not a checkpoint at all: the builder's checks say so
    if folder is None or has_full_weights(folder) or not is_lora_checkpoint(folder):
        return
    run = folder.parent.parent if folder.parent.name == C.CHECKPOINTS_DIR else folder.parent
    raise PreflightError(
        f"init.checkpoint {init_checkpoint} is a LoRA checkpoint ({folder}: the adapter only, no base weights): "
        f"start stage=rl from {run / C.MERGED_DIR_NAME}, the weights with that adapter folded in, which a LoRA "
        "run writes at its end (lora.merge_at_end); the RL run attaches fresh adapters to them"
    )


def embedded_env(cfg: TrainConfig, splits: Splits, profile: MetricProfile) -> VectorSimulator:
    """`rl.num_envs` embedded simulators rebuilding the dataset's cities at its frame size; a collision ends the
    flight when the profile fails it (no step is flown that the reward would not see)."""
    generated = read_generation_settings(cfg.data.root)
    if generated is not None:
        height, width = generated.height, generated.width
    else:
        first = splits.episodes[C.SPLIT_TRAIN][0]
        height, width = splits.frames.frame(first, 0).shape[:2]
    city = {"city": city_config(generated.city_size_m, generated.city_buildings)} if generated else {}
    sim_cfg = EmbeddedSimConfig(
        width=width,
        height=height,
        collision="end" if profile.collision_policy == "end_fail" else "count",
        max_cached_scenes=max(4, cfg.rl.num_envs),
        **city,
    )
    return VectorSimulator.embedded(sim_cfg, num_envs=cfg.rl.num_envs)


class StepBatches:
    """Collated training batches of rollout steps (the navigation collator, plus the box token's input)."""

    def __init__(self, agent: OpenFlyAgent, cfg: TrainConfig) -> None:
        self.collate = NavigationCollator(
            agent.processor, cfg.model.memory.capacity, cfg.model.keyframes.set_size
        )

    def __call__(self, samples: list[dict], device: torch.device) -> dict:
        batch = self.collate(samples)
        batch[C.TOKEN_BOX] = torch.stack([torch.as_tensor(s[C.TOKEN_BOX]) for s in samples])  # (B, 4)
        batch[C.TOKEN_BOX_VISIBLE] = torch.tensor([bool(s[C.TOKEN_BOX_VISIBLE]) for s in samples])  # (B,)
        return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def taken_log_probs(model, batch: dict, action_ids: torch.Tensor, temperature: float) -> dict:
    """The training forward on `batch`: (B,) log-probs of the labelled actions, (B,) entropies, the grounding
    loss (a scalar tensor, or None without a grounding head)."""
    outputs: dict[str, torch.Tensor] = {}
    model(batch, outputs=outputs)
    logp, entropy = action_log_probs(
        outputs["action_logits"], outputs["action_targets"], action_ids, temperature
    )
    return {"logp": logp, "entropy": entropy, "grounding_loss": outputs.get("grounding_loss")}


@dataclass
class RLSetup:
    """Everything an RL run holds between its updates (`set_up_rl`)."""

    cfg: TrainConfig
    accelerator: Any
    model: Any  # the prepared agent (what the optimizer moves)
    reference: Callable  # the starting policy, frozen, called as the agent (training/rl_reference.py)
    optimizer: Any
    scheduler: Any
    checkpoints: CheckpointManager
    state: TrainerState
    last_checkpoint: Path | None
    saved_step: int | None
    profile: MetricProfile
    max_steps: int
    batches: StepBatches
    action_ids: torch.Tensor  # (10,) the discrete action token ids
    splits: Splits


def set_up_rl(cfg: TrainConfig, embedded: bool = True) -> RLSetup:
    """The checks, the agent and its reference policy, the optimizer and a resumed state (PreflightError on bad
    input, before any compute). `embedded`: the run flies the embedded city of `cfg.data.root` (not a given
    environment), so its train scenes must be embedded ones."""
    resume_from = check_output_dir(cfg.output_dir, cfg.resume)
    data, _ = resolve_val_split(cfg.data)
    cfg = dataclasses.replace(cfg, data=data)
    setting_changes = resume_changes(cfg, resume_from)
    check_dataset_root(cfg.data)
    accelerator = make_accelerator(cfg)
    splits = load_splits(cfg.data, cfg.model.grounding)
    profile = check_rl_run(cfg, splits, accelerator.num_processes, embedded)
    checkpoints = CheckpointManager(cfg.output_dir, cfg.checkpoint.keep_last)
    checkpoints.remove_stale_staging()
    agent = prepare_agent(cfg, splits, accelerator, resume_from)  # the init.checkpoint's policy
    record_run_settings(cfg, resume_from, setting_changes)
    optim = cfg.optim
    optimizer = make_optimizer(agent, optim.lr, optim.weight_decay, optim.betas, optim.eps)
    scheduler = make_scheduler(optimizer, optim.schedule, optim.warmup_steps, cfg.steps, optim.min_lr_ratio)
    model, optimizer, scheduler = accelerator.prepare(agent, optimizer, scheduler)
    # the KL term's starting policy, made before a resume restores the trained weights
    reference = make_reference(cfg, model, accelerator.unwrap_model(model))
    logger.info("rl reference: %s", describe_reference(reference))
    register_state_hooks(accelerator)
    state, last_checkpoint, saved_step = TrainerState(), None, None
    if resume_from is not None:
        state = restore_checkpoint(accelerator, resume_from)
        last_checkpoint, saved_step = resume_from, state.step
    start_trackers(
        accelerator, cfg.logging.project, flat_config(cfg), None if resume_from is None else state.step
    )
    unwrapped = accelerator.unwrap_model(model)
    action_ids = torch.tensor(unwrapped.action_tokenizer.discrete_token_ids, device=accelerator.device)
    max_steps = cfg.rl.max_steps or profile.max_steps
    return RLSetup(
        cfg, accelerator, model, reference, optimizer, scheduler, checkpoints, state, last_checkpoint,
        saved_step, profile, max_steps, StepBatches(unwrapped, cfg), action_ids, splits,
    )  # fmt: skip


def train_rl(cfg: TrainConfig, env: VectorSimulator | None = None) -> RLRun:
    """Run the RL stage of `cfg` (module docstring); `env`: the lockstep simulator to fly in (None: the
    embedded city of `cfg.data.root`, closed at the end; a bridge's environment works the same way).

    Raises:
        PreflightError: bad input, before any compute.
    """
    owned = env is None  # an environment given by the caller stays open
    run = set_up_rl(cfg, embedded=owned)
    cfg, state, rl = run.cfg, run.state, run.cfg.rl
    logger.info(
        "rl: %d updates of %d episodes x %d rollouts (profile %s, at most %d steps), from update %d",
        cfg.steps, rl.episodes_per_update, rl.group_size, run.profile.name, run.max_steps, state.step,
    )  # fmt: skip
    env = embedded_env(cfg, run.splits, run.profile) if owned else env
    progress = progress_bar(total=cfg.steps, initial=state.step, desc="rl")
    stops = StopFlags(run.accelerator, cfg.time_limit_minutes, elapsed_before_s=state.train_seconds)
    forced_stop = forced_stop_step()  # tests only: None unless OPENFLY_STOP_AFTER_STEPS is set
    reason, crashed = None, False
    with env if owned else contextlib.nullcontext(), progress, stops, closing_trackers(run.accelerator):
        while state.step < cfg.steps and reason is None:
            logs = one_update(run, env)
            progress.update(1)
            progress.set_postfix(reward=f"{logs['reward']:.3f}", sr=f"{logs['success_rate']:.2f}")
            interval = cfg.checkpoint.save_interval
            if interval and state.step % interval == 0:
                save_rl_checkpoint(run, stops)
            if forced_stop is not None and state.step >= forced_stop:  # the test-only stop: a crash
                logger.warning(
                    "%s=%d reached: exiting without the final save", STOP_AFTER_STEPS_ENV, state.step
                )
                crashed = True
                break
            reason = stops.reason() if state.step < cfg.steps else None
        progress.close()
        if not crashed and run.saved_step != state.step:
            save_rl_checkpoint(run, stops)
    if not crashed and reason != SIGNAL:
        merge_lora_at_end(run)
    unwrapped = run.accelerator.unwrap_model(run.model)
    stopped_early = crashed or reason is not None
    return RLRun(state, run.last_checkpoint, stopped_early, unwrapped, run.accelerator.is_main_process)


def save_rl_checkpoint(run: RLSetup, stops: StopFlags) -> None:
    """A checkpoint of the run at its current update, with the training time so far."""
    run.state.train_seconds = int(stops.elapsed_s())
    run.last_checkpoint = save_checkpoint(run.accelerator, run.model, run.state, run.checkpoints, run.cfg)
    run.saved_step = run.state.step


def merge_lora_at_end(run: RLSetup) -> None:
    """A LoRA run's `<output_dir>/merged` (`lora.merge_at_end`), unless it already holds the last checkpoint's
    merge (a resume with nothing left to train), as the navigation stage writes it (training/finish.py)."""
    cfg = run.cfg
    if not (cfg.use_lora and cfg.lora.merge_at_end):
        return
    if run.last_checkpoint is not None and merged_model_of(run.last_checkpoint) is not None:
        return
    export_merged_lora(run.accelerator, run.model, cfg.output_dir)


def one_update(run: RLSetup, env: VectorSimulator) -> dict[str, float]:
    """Fly the update's groups, update the policy, step the schedule and the counters, log; returns the logs."""
    cfg, state, rl = run.cfg, run.state, run.cfg.rl
    train_episodes = run.splits.episodes[C.SPLIT_TRAIN]
    unwrapped = run.accelerator.unwrap_model(run.model)
    rng, sampler = update_seeds(cfg.seed, state.step)
    t0 = time.perf_counter()
    picks = rng.choice(len(train_episodes), rl.episodes_per_update, replace=False)
    unwrapped.eval()
    groups = collect_groups(
        unwrapped, env, [train_episodes[int(i)] for i in picks], rl, run.profile, sampler, run.max_steps
    )
    rollout_s = time.perf_counter() - t0
    micro = cfg.batch.per_device_batch_size
    logs = update_policy(
        run.model, run.reference, run.optimizer, groups, run.batches, run.action_ids, cfg, rng, micro,
        run.accelerator,
    )  # fmt: skip
    run.scheduler.step()
    logs.update(rollout_s=rollout_s, update_s=time.perf_counter() - t0 - rollout_s)
    logs["lr"] = float(run.scheduler.get_last_lr()[0])
    state.step += 1
    state.samples_seen += int(logs["rollout_steps"])
    run.accelerator.log({f"train/{k}": v for k, v in logs.items()}, step=state.step)
    logger.info(update_line(state.step, logs))
    return logs


def update_line(step: int, logs: dict[str, float]) -> str:
    """The log line of one update. An update whose groups all had equal rewards trained on nothing; it says so
    instead of printing KL, entropy and clip fraction it did not measure."""
    head = (
        f"update {step}: reward {logs['reward']:.3f}, success {logs['success_rate']:.3f}, "
        f"groups with signal {logs['groups_with_signal']:.2f}"
    )
    if "kl" not in logs:
        return f"{head}; no group with signal, the policy is unchanged"
    return f"{head}, kl {logs['kl']:.4f}, entropy {logs['entropy']:.3f}, clip {logs['clip_fraction']:.3f}"


def update_policy(
    model,
    reference,
    optimizer,
    groups: list[list[Rollout]],
    batches,
    action_ids,
    cfg,
    rng,
    micro,
    accelerator,
) -> dict[str, float]:
    """Steps 2-4 of an update (module docstring) on the flown `groups`; returns the update's logs."""
    rl = cfg.rl
    rewards = torch.tensor([[r.reward for r in group] for group in groups], dtype=torch.float64)  # (N, G)
    advantages = group_advantages(rewards)  # (N, G)
    kept = [
        (step_sample(r.record, r.steps, t), float(advantages[n, g]), r.steps[t].boxes_known)
        for n, group in enumerate(groups)
        if bool(rewards[n].std() > 0)
        for g, r in enumerate(group)
        for t in range(len(r.steps))
    ]
    logs = {
        "reward": float(rewards.mean()),
        "success_rate": float(np.mean([r.success for group in groups for r in group])),
        "groups_with_signal": float(np.mean([bool(rewards[n].std() > 0) for n in range(len(groups))])),
        "rollout_steps": float(sum(len(r.steps) for group in groups for r in group)),
        "samples_trained": float(len(kept)),
    }
    if not kept:
        return logs
    old_logp, ref_logp = starting_log_probs(
        model, reference, kept, batches, action_ids, rl.temperature, micro
    )
    advantage = torch.tensor([a for _, a, _ in kept])  # (K,)
    means = RunningMeans()
    for _ in range(rl.epochs):
        order = rng.permutation(len(kept))
        for minibatch in np.array_split(order, rl.minibatches):
            if len(minibatch) > 0:
                means.add(
                    minibatch_step(
                        model, optimizer, kept, minibatch, (old_logp, ref_logp, advantage), batches,
                        action_ids, cfg, micro, accelerator, means,
                    )
                )  # fmt: skip
    optimizer.zero_grad(set_to_none=True)
    logs.update(means.pop())
    return logs


def starting_log_probs(model, reference, kept, batches, action_ids, temperature, micro):
    """(K,) log-probs of the kept steps' taken actions under the update's starting policy and under the frozen
    reference, in eval mode (the rollout's network path: no box jitter, BatchNorm's running statistics)."""
    device = next(model.parameters()).device
    chunks = [list(range(i, min(i + micro, len(kept)))) for i in range(0, len(kept), micro)]
    old_logp, ref_logp = torch.empty(len(kept)), torch.empty(len(kept))
    model.eval()
    with torch.no_grad():
        for chunk in chunks:
            batch = batches([kept[i][0] for i in chunk], device)
            old_logp[chunk] = taken_log_probs(model, batch, action_ids, temperature)["logp"].float().cpu()
            ref_logp[chunk] = taken_log_probs(reference, batch, action_ids, temperature)["logp"].float().cpu()
    return old_logp, ref_logp


def minibatch_step(
    model, optimizer, kept, minibatch, starting, batches, action_ids, cfg, micro, accelerator, means
) -> dict[str, float]:
    """One optimizer step on a minibatch of kept steps (micro-batches of `micro`); returns its mean figures.
    `starting`: the (K,) old and reference log-probs and the advantages."""
    rl, device = cfg.rl, accelerator.device
    old_logp, ref_logp, advantage = starting
    optimizer.zero_grad(set_to_none=True)
    sums = {"pg_loss": 0.0, "kl": 0.0, "clipped": 0.0, "entropy": 0.0}
    for start in range(0, len(minibatch), micro):
        rows = [int(i) for i in minibatch[start : start + micro]]
        batch = batches([kept[i][0] for i in rows], device)
        out = taken_log_probs(model, batch, action_ids, rl.temperature)
        total, parts = rl_loss(
            out["logp"], old_logp[rows].to(device), ref_logp[rows].to(device), advantage[rows].to(device),
            rl.clip_epsilon, rl.kl_coef,
        )  # fmt: skip
        loss = total / len(minibatch)
        grounding = out["grounding_loss"]
        if grounding is not None and rl.grounding_weight and all(kept[i][2] for i in rows):
            loss = loss + rl.grounding_weight * grounding * len(rows) / len(minibatch)
            means.add({"grounding_loss": float(grounding.detach())})
        accelerator.backward(loss)
        for key, value in parts.items():
            sums[key] += float(value)
        sums["entropy"] += float(out["entropy"].detach().sum())
    if cfg.optim.max_grad_norm is not None:
        grad_norm = accelerator.clip_grad_norm_(model.parameters(), cfg.optim.max_grad_norm)
        means.add({"grad_norm": float(grad_norm)})
    optimizer.step()
    count = len(minibatch)
    return {
        "pg_loss": sums["pg_loss"] / count,
        "kl": sums["kl"] / count,
        "clip_fraction": sums["clipped"] / count,
        "entropy": sums["entropy"] / count,
    }

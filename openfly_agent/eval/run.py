"""`run(cfg)`: evaluate the configured policy and baselines on every split, resumably, then report.

Per policy: check that `<output_dir>/<policy>/` holds results of the same settings (or start over with
`overwrite`), skip episodes already in its logs, run the rest of this process' shard, and append each
finished episode to the log. Rank 0 then merges the logs and recomputes every table from them.
"""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

from openfly_agent.data.schema import Episode
from openfly_agent.eval.baselines import OraclePolicy
from openfly_agent.eval.config import AGENT_POLICIES, TRUE_BOX_LEG, EvalConfig, EvalInputError
from openfly_agent.eval.distributed import (
    ProcessInfo,
    log_name,
    merge_logs,
    process_info,
    read_all_logs,
    shard,
)
from openfly_agent.eval.factory import (
    check_simulator_scenes,
    embedded_sim_config,
    load_full_splits,
    make_env,
    make_policy,
    subsample_splits,
)
from openfly_agent.eval.outputs import write_policy_outputs, write_summary
from openfly_agent.eval.plots import safe_name, write_gif
from openfly_agent.eval.records import EpisodeLog
from openfly_agent.eval.report import scored
from openfly_agent.eval.rollout import FrameLog, FrameRecorder, teleport_record
from openfly_agent.model.persistence.checkpoint_path import UnreadableWeightsError, check_weights_readable
from openfly_agent.rollout.checkpoints import (
    CheckpointError,
    checkpoint_fingerprint,
    checkpoint_folder,
    describe_weights_change,
)
from openfly_agent.rollout.legs import CurrentLegBox
from openfly_agent.rollout.policy import Policy
from openfly_agent.rollout.record import EpisodeRecord
from openfly_agent.rollout.runner import LockstepRunner, RolloutStats, groups
from openfly_agent.sim.vector import VectorSimulator

logger = logging.getLogger(__name__)

RUN_IDENTITY_NAME = "run_identity.json"


def prepare_output(folder: Path, identity: dict, overwrite: bool, info: ProcessInfo) -> None:
    """Make `folder` ready for this run: refuse to mix results of different settings unless `overwrite`.

    Every process checks (so all of them fail together, none waits at a barrier alone); rank 0 writes.
    """
    path = folder / RUN_IDENTITY_NAME
    stored = read_run_identity(folder)
    if stored is not None and not overwrite:
        # both sides' keys: a setting recorded only when it is not its default (agent.memory_probe) counts too
        keys = list(identity) + [k for k in stored if k not in identity]
        changed = {k: (stored.get(k), identity.get(k)) for k in keys if stored.get(k) != identity.get(k)}
        if changed:
            details = ", ".join(_describe_change(k, old, new) for k, (old, new) in changed.items())
            raise EvalInputError(
                f"{folder} holds results of other settings ({details}); pass another --output_dir "
                "or --overwrite=true to discard them"
            )
    info.wait()
    if info.is_main:
        if overwrite and folder.exists():
            shutil.rmtree(folder)
        folder.mkdir(parents=True, exist_ok=True)
        if not path.is_file():
            path.write_text(json.dumps(identity, indent=2, sort_keys=True) + "\n")
    info.wait()


def _describe_change(key: str, old, new) -> str:
    """`max_steps: 100 -> 50`; for the agent's weights, which file changed and when (not raw fingerprints)."""
    if key == "weights" and isinstance(old, dict) and isinstance(new, dict):
        return f"weights: {describe_weights_change(old, new)}"
    return f"{key}: {old!r} -> {new!r}"


def read_run_identity(folder: Path) -> dict | None:
    """The `run_identity.json` of a policy's results folder (settings, and the agent's `weights`); None if absent."""
    path = folder / RUN_IDENTITY_NAME
    return json.loads(path.read_text()) if path.is_file() else None


def same_weights(recorded: dict, current: dict) -> bool:
    """Whether two `checkpoint_fingerprint`s are the same weights: the same weight files with the same sizes and
    modification times (a run folder moved with its files still matches); without weight files, the same folder."""
    if recorded.get("weights") or current.get("weights"):
        return recorded.get("weights") == current.get("weights")
    return recorded.get("folder") == current.get("folder")


def result_identity(cfg: EvalConfig, policy: str) -> dict:
    """`cfg.result_identity(policy)`, plus the fingerprint of the agent's weights."""
    identity = cfg.result_identity(policy)
    if policy in AGENT_POLICIES:
        identity["weights"] = checkpoint_fingerprint(cfg.checkpoint)
    return identity


def check_agent_weights(cfg: EvalConfig) -> None:
    """A truncated or corrupt weights file of the agent fails here, in one line, before any output is written."""
    if not any(name in AGENT_POLICIES for name in cfg.policies):
        return
    try:
        check_weights_readable(checkpoint_folder(cfg.checkpoint))
    except (UnreadableWeightsError, CheckpointError) as err:
        raise EvalInputError(str(err)) from None


def gif_path(folder: Path, split: str, episode_id: str) -> Path:
    """Where the GIF of one episode goes."""
    return folder / "gifs" / f"{split}__{safe_name(episode_id)}.gif"


def evaluate_policy(
    cfg: EvalConfig,
    policy: Policy,
    episodes_by_split: dict[str, list[Episode]],
    env: VectorSimulator,
    folder: Path,
    info: ProcessInfo,
) -> RolloutStats:
    """Run this process' shard of every split not yet in the logs of `folder`; append as they finish."""
    # Errored episodes (an engine that failed) are not done: this run tries them again.
    logged = read_all_logs(folder)
    done = {r.key for r in logged if not r.errored}
    errored = {r.key for r in logged if r.errored}
    log = EpisodeLog(folder / log_name(info))
    gif_ids = set(cfg.gif_episodes)

    def save_gif(record: EpisodeRecord, frames: FrameLog) -> None:
        write_gif(frames, record.actions, gif_path(folder, record.split, record.episode_id))

    hooks = [FrameRecorder(gif_ids, save_gif)]
    if cfg.true_box == TRUE_BOX_LEG and policy.features.target_box:
        hooks.append(CurrentLegBox())
    runner = LockstepRunner(policy, env, cfg.max_steps, hooks, show_progress=cfg.progress)
    for split, episodes in episodes_by_split.items():
        mine = shard(episodes, info.rank, info.world_size)
        todo = [e for e in mine if (split, e.episode_id) not in done]
        retried = sum((split, e.episode_id) in errored for e in todo)
        # logged by rank 0 only (utils/logging_utils.py), so it names every process's shard
        shard_sizes = [len(shard(episodes, rank, info.world_size)) for rank in range(info.world_size)]
        logger.info(
            "%s / %s: %d episodes%s, %d already done%s",
            policy.name,
            split,
            len(episodes),
            f" in {info.world_size} shards of {', '.join(map(str, shard_sizes))}"
            if info.world_size > 1
            else "",
            sum((split, e.episode_id) in done for e in episodes),
            f", {retried} that ended in an engine error tried again" if retried else "",
        )
        if isinstance(policy, OraclePolicy):  # episodes whose actions do not replay follow the recorded poses
            for episode in [e for e in todo if not policy.replays(e.episode_id)]:
                log.append(scored(teleport_record(episode, split, policy.name, cfg.max_steps), cfg.profiles))
            mine = [e for e in mine if policy.replays(e.episode_id)]

        def unfinished(record: EpisodeRecord, split: str = split) -> None:
            if (split, record.episode_id) not in done:  # an already logged companion recomputed identically
                log.append(scored(record, cfg.profiles))

        # Resume by whole lockstep groups: a group that lost episodes to a kill runs again with the same
        # companions, so its records are bit-identical to an uninterrupted run's (docs/EVAL.md).
        pending = [g for g in groups(mine, env.num_envs) if any((split, e.episode_id) not in done for e in g)]
        runner.run([e for g in pending for e in g], split, on_finish=unfinished)
        missing = {
            e.episode_id
            for e in mine
            if e.episode_id in gif_ids
            and (split, e.episode_id) in done
            and not gif_path(folder, split, e.episode_id).is_file()
        }
        replay = [g for g in groups(mine, env.num_envs) if missing & {e.episode_id for e in g}]
        if replay:  # finished in an earlier run: replay their groups (bit-identical) to get the frames
            runner.run([e for g in replay for e in g], split)
    return runner.stats


def run(cfg: EvalConfig) -> dict:
    """Evaluate `cfg.policies` on `cfg.split`; returns {"summary_markdown", "results": {policy: results}}.

    Every process runs its shard; only rank 0 merges, writes reports and returns the tables (other ranks
    return an empty dict). The process's torch thread count (`cfg.torch_threads`) is the entry point's to set
    (eval.py): an in-process caller (a test, a notebook) keeps its own, and so its numerics.
    """
    info = process_info(cpu=True if cfg.device == "cpu" else None)
    root = Path(cfg.output_dir)
    check_agent_weights(cfg)
    full_splits = load_full_splits(cfg)
    episodes_by_split = subsample_splits(full_splits, cfg.max_episodes)
    split_sizes = {split: len(episodes) for split, episodes in full_splits.items()}  # before max_episodes
    all_episodes = [e for eps in episodes_by_split.values() for e in eps]
    check_simulator_scenes(cfg, all_episodes)  # before a model loads or an output folder is made
    envs: dict[bool, VectorSimulator] = {}  # rendering or blind (baselines never look at frames)
    if cfg.sim.type != "embedded":  # connect now: an engine that cannot be reached fails before any output
        envs[True] = envs[False] = make_env(cfg, info, all_episodes)
    try:
        for name in cfg.policies:
            folder = root / name
            prepare_output(folder, result_identity(cfg, name), cfg.overwrite, info)
            policy = make_policy(name, cfg, all_episodes, info)
            render = bool(policy.features.frames or cfg.gif_episodes)
            if render not in envs:
                envs[render] = make_env(cfg, info, all_episodes, render=render)
            stats = evaluate_policy(cfg, policy, episodes_by_split, envs[render], folder, info)
            logger.info(
                "%s: %d episodes, %d steps, simulator %.1f s, policy %.1f s",
                name, stats.episodes, stats.steps, stats.sim_s, stats.policy_s,
            )  # fmt: skip
            del policy
    finally:
        for env in {id(env): env for env in envs.values()}.values():
            env.close()
    info.wait()
    if not info.is_main:
        return {}
    all_results = {}
    wanted = expected_keys(episodes_by_split)
    city = embedded_sim_config(cfg, all_episodes).city if cfg.sim.type == "embedded" else None
    for name in cfg.policies:
        records = [r for r in merge_logs(root / name) if r.key in wanted]
        if len(records) != len(wanted):
            raise RuntimeError(
                f"{root / name}: {len(wanted) - len(records)} episodes have no record after the run"
            )
        all_results[name] = write_policy_outputs(
            cfg, name, records, root / name, episodes_by_split, city, split_sizes
        )
    summary = write_summary(cfg, list(all_results.values()), root)
    errors = {name: results_errors(results) for name, results in all_results.items()}
    return {"summary_markdown": summary, "results": all_results, "output_dir": str(root), "errors": errors}


def results_errors(results: dict) -> int:
    """Episodes of a policy's results that ended in an engine error (not scored), over all splits."""
    return sum(results.get("errors", {}).values())


def expected_keys(episodes_by_split: dict[str, list[Episode]]) -> set[tuple[str, str]]:
    """(split, episode id) of every episode the run covers."""
    return {(split, e.episode_id) for split, eps in episodes_by_split.items() for e in eps}

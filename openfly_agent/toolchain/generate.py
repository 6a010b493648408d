"""Scenes -> dataset: work units, spawn workers with scene affinity, resume, shards, instructions, summary.

The parent decides the units (scene seed, trajectory index, split), skips those the ledger already holds,
hands whole scenes to worker processes (spawn context: EGL contexts are not fork-safe; one simulator and
one prepared scene at a time per worker), collects results, generates instructions in batches (VLM
concurrency) and writes every episode through `OpenFlyDatasetWriter`. Shard i/N takes the scenes at
positions i, i + N, ... of the scene list, so N machines write disjoint folders that merge by copying.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import queue
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from openfly_agent import constants as C
from openfly_agent.data.writer import OpenFlyDatasetWriter
from openfly_agent.sim.base import Simulator
from openfly_agent.sim.city import scene_id_of
from openfly_agent.toolchain.config import VAL_INDEX_BASE, GenerateConfig, parse_shard
from openfly_agent.toolchain.instructions import make_instruction_backend
from openfly_agent.toolchain.ledger import STATUS_OK, STATUS_REJECTED, UnitLedger
from openfly_agent.toolchain.pipeline import KIND_ASTAR, KIND_DAGGER, KIND_DAGGER_POLICY, UnitResult, WorkUnit
from openfly_agent.toolchain.settings import prepare_output, record_kept_on_success
from openfly_agent.toolchain.summary import write_summary
from openfly_agent.toolchain.worker import SceneWorker, default_simulator
from openfly_agent.utils.progress import progress_bar

logger = logging.getLogger(__name__)
_SPLIT_STREAM = 7  # seed stream of the test-seen draw, apart from the route seeds
_RESULT_TIMEOUT_S = 5.0


# What a scene is generated for: its A* units go to train / test_seen (and val), test_unseen, or val
ROLE_TRAIN, ROLE_UNSEEN, ROLE_VAL = "train", "unseen", "val"


def shard_scenes(cfg: GenerateConfig) -> list[tuple[int, str]]:
    """(seed, role) of the scenes this shard generates, in config order (train, unseen, then validation seeds).

    The validation cities come last, so adding them leaves the shard of every other scene as it was.
    """
    index, count = parse_shard(cfg.shard)
    scenes = (
        [(s, ROLE_TRAIN) for s in cfg.scenes.train_seeds]
        + [(s, ROLE_UNSEEN) for s in cfg.scenes.unseen_seeds]
        + [(s, ROLE_VAL) for s in cfg.scenes.val_seeds]
    )
    return [scene for position, scene in enumerate(scenes) if position % count == index]


def scene_units(
    seed: int, role: str, cfg: GenerateConfig, kinds: tuple[str, ...] = (KIND_ASTAR, KIND_DAGGER)
) -> list[WorkUnit]:
    """The units of a scene of `role`; train-scene A* units go to test_seen with probability `test_seen_fraction`.

    Validation units (train scenes: `val_seen_per_scene`, validation scenes: `val_unseen_per_scene`) are
    numbered from `VAL_INDEX_BASE`: their seeds are a stream of their own, so the units of the other splits are
    the same with or without them. DAgger units (`dagger.episodes_per_scene` of each requested dagger kind)
    exist in train scenes only.
    """
    units = []
    scenes = cfg.scenes
    if KIND_ASTAR in kinds and role != ROLE_VAL:
        for index in range(scenes.trajectories_per_scene):
            if role == ROLE_UNSEEN:
                split = C.SPLIT_TEST_UNSEEN
            else:
                draw = np.random.default_rng([cfg.seed, seed, index, _SPLIT_STREAM]).random()
                split = C.SPLIT_TEST_SEEN if draw < scenes.test_seen_fraction else C.SPLIT_TRAIN
            units.append(WorkUnit(seed, index, split, KIND_ASTAR))
    for kind in (KIND_DAGGER, KIND_DAGGER_POLICY):
        if kind in kinds and role == ROLE_TRAIN:
            units += [WorkUnit(seed, i, C.SPLIT_TRAIN, kind) for i in range(cfg.dagger.episodes_per_scene)]
    if KIND_ASTAR in kinds and role != ROLE_UNSEEN:
        count = scenes.val_unseen_per_scene if role == ROLE_VAL else scenes.val_seen_per_scene
        units += [WorkUnit(seed, VAL_INDEX_BASE + i, C.SPLIT_VAL, KIND_ASTAR) for i in range(count)]
    return units


def pending_units(
    cfg: GenerateConfig, ledger: UnitLedger, writer: OpenFlyDatasetWriter, kinds: tuple[str, ...]
) -> dict[int, list[WorkUnit]]:
    """Units per scene seed that are not finished yet (a ledger line, and the episode exists if it was ok)."""
    todo = {}
    for seed, role in shard_scenes(cfg):
        done = set()
        for record in ledger.read(scene_id_of(seed)):
            if record["status"] == STATUS_REJECTED or writer.has_episode(record["episode_id"]):
                done.add((record["index"], record["kind"]))
        todo[seed] = [u for u in scene_units(seed, role, cfg, kinds) if (u.index, u.kind) not in done]
    return todo


def _assign_scenes(todo: dict[int, list[WorkUnit]], workers: int) -> list[list[int]]:
    """Scenes per worker, balanced by unit count (largest first)."""
    loads, assignment = [0] * workers, [[] for _ in range(workers)]
    for seed in sorted(todo, key=lambda s: -len(todo[s])):
        w = int(np.argmin(loads))
        assignment[w].append(seed)
        loads[w] += len(todo[seed])
    return assignment


def _worker_main(cfg, sim_factory, seeds, units, results) -> None:
    """Worker process: one simulator, scenes in turn, one result per unit; ('error', text) on a crash."""
    # Mesa llvmpipe rasterises with one thread per core by default; share the cores between workers.
    os.environ.setdefault("LP_NUM_THREADS", str(max(1, (os.cpu_count() or 1) // max(1, cfg.workers))))
    try:
        worker = SceneWorker(cfg, sim_factory)
        try:
            for seed in seeds:
                for unit in units[seed]:
                    results.put(worker.run(unit))
        finally:
            worker.close()
        results.put(("done", None))
    except BaseException:  # reported to the parent, which raises it
        results.put(("error", traceback.format_exc()))


def _results_in_process(cfg, sim_factory, todo, policy=None) -> Iterator[UnitResult]:
    worker = SceneWorker(cfg, sim_factory, policy)
    try:
        for units in todo.values():
            for unit in units:
                yield worker.run(unit)
    finally:
        worker.close()


def _results_from_workers(cfg, sim_factory, todo) -> Iterator[UnitResult]:
    ctx = mp.get_context("spawn")
    results = ctx.Queue(maxsize=64)
    seeds_per_worker = [s for s in _assign_scenes(todo, cfg.workers) if s]
    procs = [
        ctx.Process(target=_worker_main, args=(cfg, sim_factory, seeds, {s: todo[s] for s in seeds}, results))
        for seeds in seeds_per_worker
    ]
    for proc in procs:
        proc.start()
    running = len(procs)
    try:
        while running:
            try:
                item = results.get(timeout=_RESULT_TIMEOUT_S)
            except queue.Empty:
                dead = [p for p in procs if not p.is_alive() and p.exitcode not in (0, None)]
                if dead:
                    raise RuntimeError(f"a generate worker died (exit code {dead[0].exitcode})") from None
                continue
            if isinstance(item, tuple):
                if item[0] == "error":
                    raise RuntimeError(f"a generate worker failed:\n{item[1]}")
                running -= 1
                continue
            yield item
    finally:
        for proc in procs:
            if proc.is_alive():
                proc.terminate()
            proc.join(timeout=10)


def _ledger_record(result: UnitResult, scene_id: str, status: str, reason: str | None = None) -> dict:
    record = {"index": result.unit.index, "kind": result.unit.kind, "split": result.unit.split}
    record.update(scene_id=scene_id, status=status, **({"reason": reason} if reason else {}), **result.stats)
    if status == STATUS_OK:
        episode = result.episode
        record.update(
            episode_id=episode.episode_id,
            category=episode.category,
            instruction=episode.instruction,
            actions=[int(a) for a in episode.actions],
        )
    return record


class _Sink:
    """Parent side: instructions in batches, then writer + ledger, on one background thread.

    Collecting results (main thread) overlaps with writing the previous batch (PNG encoding and parquet
    writing release the GIL); at most two batches are held in memory. The writer and the ledger are only
    touched by the background thread.
    """

    def __init__(self, cfg: GenerateConfig, writer: OpenFlyDatasetWriter, ledger: UnitLedger):
        self.cfg, self.writer, self.ledger = cfg, writer, ledger
        self.backend = make_instruction_backend(cfg.instructions)
        self.pending: list[UnitResult] = []
        self.written = 0
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="toolchain-writer")
        self._running: Future | None = None

    def add(self, result: UnitResult) -> None:
        self.pending.append(result)
        if sum(r.reason is None for r in self.pending) >= self.cfg.instruction_batch:
            self.flush(wait=False)

    def flush(self, wait: bool = True) -> None:
        """Hand the pending results to the writer thread (after the previous batch is done)."""
        if self._running is not None:
            self._running.result()  # re-raises a writer error here
            self._running = None
        batch, self.pending = self.pending, []
        if batch:
            self._running = self._pool.submit(self._write, batch)
        if wait and self._running is not None:
            self._running.result()
            self._running = None

    def close(self) -> None:
        self.flush(wait=True)
        self._pool.shutdown()

    def _write(self, batch: list[UnitResult]) -> None:
        done = [r for r in batch if r.reason is None]
        texts = iter(self.backend.generate([r.request for r in done]) if done else [])
        for result in batch:
            scene_id = scene_id_of(result.unit.scene_seed)
            text = next(texts) if result.reason is None else None
            if result.reason is not None or not text:
                reason = result.reason or "instruction_failed"
                self.ledger.append(scene_id, _ledger_record(result, scene_id, STATUS_REJECTED, reason))
                continue
            result.episode.instruction = text
            self.writer.write_episode(result.episode, result.frames)
            self.ledger.append(scene_id, _ledger_record(result, scene_id, STATUS_OK))
            self.written += 1


def generate(
    cfg: GenerateConfig,
    sim_factory: Callable[[GenerateConfig], Simulator] = default_simulator,
    progress: bool = True,
    policy=None,
    kinds: tuple[str, ...] = (KIND_ASTAR, KIND_DAGGER),
) -> dict:
    """Generate (or resume) this shard of the dataset under `cfg.output_dir`; returns the summary.

    A folder that holds a dataset of other settings is refused (`toolchain/settings.py`) unless
    `cfg.overwrite`, which discards it first.

    Args:
        cfg: the generate config.
        sim_factory: builds one simulator per worker from the config (a module-level function, so it
            pickles for spawn). Default: the embedded simulator at `cfg.render` size.
        progress: show a tqdm bar.
        policy: a `dagger.Policy` for `dagger_policy` units; runs in this process (one model copy).
        kinds: which unit kinds to generate (A* routes, noisy-expert and / or policy DAgger episodes).
    """
    with record_kept_on_success(Path(cfg.output_dir)):
        return _generate(cfg, sim_factory, progress, policy, kinds)


def _generate(cfg: GenerateConfig, sim_factory, progress: bool, policy, kinds: tuple[str, ...]) -> dict:
    root = Path(cfg.output_dir)
    root.mkdir(parents=True, exist_ok=True)
    # The policy DAgger command adds episodes to a dataset with DAgger settings of its own.
    dagger_only = KIND_ASTAR not in kinds and KIND_DAGGER not in kinds
    prepare_output(cfg, ignore=("dagger.",) if dagger_only else (), record=not dagger_only)
    writer, ledger = OpenFlyDatasetWriter(root), UnitLedger(root)
    todo = {seed: units for seed, units in pending_units(cfg, ledger, writer, kinds).items() if units}
    total = sum(len(units) for units in todo.values())
    logger.info("generate %s (shard %s): %d units to do in %d scenes", root, cfg.shard, total, len(todo))
    if total:
        if cfg.workers > 0 and policy is None:
            stream = _results_from_workers(cfg, sim_factory, todo)
        else:
            stream = _results_in_process(cfg, sim_factory, todo, policy)
        sink = _Sink(cfg, writer, ledger)
        try:
            with progress_bar(total=total, desc="trajectories", unit="traj", disable=not progress) as bar:
                for result in stream:
                    sink.add(result)
                    bar.update(1)
                    bar.set_postfix(written=sink.written, refresh=False)
        finally:
            sink.close()  # what arrived is written (and recorded) even when a worker failed
    writer.finalize()
    return write_summary(root, plots=cfg.plots)

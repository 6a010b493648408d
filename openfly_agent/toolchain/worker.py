"""What runs inside one generate worker: a simulator and the prepared scene it is working on."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from openfly_agent.sim.base import Simulator
from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator
from openfly_agent.toolchain.config import GenerateConfig
from openfly_agent.toolchain.dagger import generate_dagger_unit
from openfly_agent.toolchain.pipeline import (
    DAGGER_KINDS,
    KIND_DAGGER_POLICY,
    PreparedScene,
    UnitResult,
    WorkUnit,
    generate_unit,
    prepare_scene,
)
from openfly_agent.toolchain.scenes import city_config_for, embedded_scene

logger = logging.getLogger(__name__)


def default_simulator(cfg: GenerateConfig) -> Simulator:
    """The embedded simulator at the configured frame size, building the same cities as the toolchain."""
    sim_cfg = EmbeddedSimConfig(
        width=cfg.render.width, height=cfg.render.height, city=city_config_for(cfg.scenes)
    )
    return EmbeddedSimulator(sim_cfg)


class SceneWorker:
    """Holds one simulator (created lazily, in the process that uses it) and the current prepared scene.

    `policy` (a dagger.Policy) flies the `dagger_policy` units; `dagger` units use the noisy expert.
    """

    def __init__(
        self,
        cfg: GenerateConfig,
        sim_factory: Callable[[GenerateConfig], Simulator] = default_simulator,
        policy=None,
    ):
        self.cfg, self.sim_factory, self.policy = cfg, sim_factory, policy
        self._sim: Simulator | None = None
        self._scene: tuple[int, PreparedScene] | None = None

    @property
    def sim(self) -> Simulator:
        if self._sim is None:
            self._sim = self.sim_factory(self.cfg)
        return self._sim

    def scene(self, seed: int) -> PreparedScene:
        """The prepared embedded scene of `seed` (one kept at a time: units arrive scene by scene)."""
        if self._scene is None or self._scene[0] != seed:
            start = time.perf_counter()
            self._scene = (seed, prepare_scene(embedded_scene(seed, self.cfg.scenes), self.cfg))
            logger.info("prepared scene %d in %.1f s", seed, time.perf_counter() - start)
        return self._scene[1]

    def run(self, unit: WorkUnit) -> UnitResult:
        prepared = self.scene(unit.scene_seed)
        if unit.kind in DAGGER_KINDS:
            if unit.kind == KIND_DAGGER_POLICY and self.policy is None:
                raise ValueError("dagger_policy units need a policy (the `dagger` command loads one)")
            policy = self.policy if unit.kind == KIND_DAGGER_POLICY else None
            return generate_dagger_unit(prepared, self.sim, unit, self.cfg, policy)
        return generate_unit(prepared, self.sim, unit, self.cfg)

    def close(self) -> None:
        if self._sim is not None:
            self._sim.close()
            self._sim = None

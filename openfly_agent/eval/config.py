"""`EvalConfig`: what `eval.py` evaluates, on which data and simulator, and where results go.

Parsed with draccus from YAML (`configs/eval/*.yaml`) and dotted command-line overrides. The simulator
is a registered choice (`--sim.type=unrealcv`) whose engine variants hold the bridges' own config dataclasses
(`--sim.unrealcv.port=9001`), so no setting is declared twice.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

from draccus import ChoiceRegistry

from openfly_agent import constants as C
from openfly_agent.data.config import ReaderOptions
from openfly_agent.eval.box_servo import BoxServoSettings
from openfly_agent.sim.bridges.airsim import AirSimBridge, AirSimConfig
from openfly_agent.sim.bridges.base import EngineBridge
from openfly_agent.sim.bridges.gs_http import GSHttpBridge, GSHttpConfig
from openfly_agent.sim.bridges.unrealcv import UnrealCVBridge, UnrealCVConfig


class EvalInputError(ValueError):
    """Input that cannot be evaluated (settings that clash with an output folder, an empty split, an unknown
    checkpoint type); raised before any episode runs, with a message that says what to change."""


class EngineUnreachableError(EvalInputError):
    """The simulator engine of `--sim` cannot be reached; raised before the first episode, naming the engine,
    host and port."""


# the agent of --checkpoint fed the simulator's true target box (embedded only)
AGENT_TRUE_BOX = "agent_true_box"
AGENT_POLICIES = ("agent", AGENT_TRUE_BOX)  # the policies that load --checkpoint
TRUE_BOX_POLICIES = ("box_servo", AGENT_TRUE_BOX)  # the policies that read the true target box
POLICY_NAMES = ("agent", "random", "stop", "forward", "oracle", "box_servo", AGENT_TRUE_BOX)
# whose true box agent_true_box reads: the route's last target, or the target of the leg the drone is on
TRUE_BOX_FINAL, TRUE_BOX_LEG = "final", "leg"
TRUE_BOX_TARGETS = (TRUE_BOX_FINAL, TRUE_BOX_LEG)
SIM_EMBEDDED = "embedded"  # the default simulator; the others are engines reached through a bridge
PROFILE_NAMES = ("openfly", "standard")
ORACLE_MODES = ("auto", "replay", "teleport")
DECODE_RULES = ("exact", "nearest")


@dataclass
class SimSettings(ChoiceRegistry):
    """The simulator episodes run in: one registered choice per simulator (`type:` in YAML, `--sim.type=` on the
    command line), each with only its own fields.

    `embedded` (the default, `EmbeddedSimSettings`) renders the procedural city of each `embedded-<seed>` scene;
    `unrealcv`, `airsim` and `gs_http` (`BridgeSimSettings`) connect to a running engine (docs/BRIDGES.md, one
    engine per process). Collisions are recorded and never end an episode: each metric profile decides what a
    collision means (docs/EVAL.md).
    """

    @classmethod
    def default_choice_name(cls) -> str:
        return SIM_EMBEDDED

    @property
    def type(self) -> str:
        """The registered name of this simulator (`embedded`, `unrealcv`, `airsim`, `gs_http`)."""
        return self.get_choice_name(type(self))

    def result_identity(self) -> dict:
        """The simulator settings that decide an episode's results (part of `EvalConfig.result_identity`)."""
        raise NotImplementedError


@SimSettings.register_subclass(SIM_EMBEDDED)
@dataclass
class EmbeddedSimSettings(SimSettings):
    """`embedded`: the procedural city of each `embedded-<seed>` scene; the city parameters and, by default, the
    frame size come from the dataset's generation settings (data/generation_settings.py)."""

    width: int | None = None  # frame size; None = the dataset's (generation settings, else a frame)
    height: int | None = None

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if value is not None and value < 16:
                raise ValueError(
                    f"sim.{name}={value}: frames must be at least 16 pixels (or null for the dataset's)"
                )

    def result_identity(self) -> dict:
        return {
            "sim_type": self.type,
            "sim_width": self.width,
            "sim_height": self.height,
            "sim_occupancy": None,
        }


@dataclass
class BridgeSimSettings(SimSettings):
    """A running engine reached through its bridge (docs/BRIDGES.md); each engine's variant names its bridge class
    (`bridge_class`) and adds the bridge's own config as the section of its name (`--sim.unrealcv.port=9001`)."""

    bridge_class: ClassVar[type[EngineBridge]]  # the bridge this variant connects with

    # a point cloud per scene for collision checks, e.g. "scenes/{scene_id}.pcd" (None = no check, as the
    # official evaluation); voxel size of the occupancy built from it
    occupancy_pcd: str | None = None
    occupancy_voxel_m: float = 2.0
    port_per_rank: bool = True  # under a launcher: process k connects to port + k

    def __post_init__(self) -> None:
        if self.occupancy_pcd is not None and "{scene_id}" not in self.occupancy_pcd:
            raise ValueError(f"sim.occupancy_pcd={self.occupancy_pcd!r} must contain '{{scene_id}}'")
        if self.occupancy_voxel_m <= 0:
            raise ValueError(f"sim.occupancy_voxel_m={self.occupancy_voxel_m} must be > 0 metres")

    def bridge_config(self) -> UnrealCVConfig | AirSimConfig | GSHttpConfig:
        """The settings of this engine's bridge (the section named after it)."""
        return getattr(self, self.type)

    def result_identity(self) -> dict:
        return {
            "sim_type": self.type,
            "sim_width": None,
            "sim_height": None,
            "sim_occupancy": self.occupancy_pcd,
        }


@SimSettings.register_subclass("unrealcv")
@dataclass
class UnrealCVSimSettings(BridgeSimSettings):
    """`unrealcv`: a UE scene through the UnrealCV TCP server."""

    bridge_class: ClassVar[type[EngineBridge]] = UnrealCVBridge
    unrealcv: UnrealCVConfig = field(default_factory=UnrealCVConfig)


@SimSettings.register_subclass("airsim")
@dataclass
class AirSimSimSettings(BridgeSimSettings):
    """`airsim`: an AirSim scene through its msgpack-RPC server."""

    bridge_class: ClassVar[type[EngineBridge]] = AirSimBridge
    airsim: AirSimConfig = field(default_factory=AirSimConfig)


@SimSettings.register_subclass("gs_http")
@dataclass
class GSHttpSimSettings(BridgeSimSettings):
    """`gs_http`: a 3DGS scene served over HTTP by the patched SIBR viewer."""

    bridge_class: ClassVar[type[EngineBridge]] = GSHttpBridge
    gs_http: GSHttpConfig = field(default_factory=GSHttpConfig)


@dataclass
class AgentSettings:
    """How a checkpoint is loaded and decoded (used when `policy` is `agent`)."""

    unnorm_key: str | None = None  # openvla_bins head: norm-stats key (released model: vlnv1 or vln_norm)
    decode_rule: str | None = None  # openvla_bins head: exact | nearest; None = the checkpoint's setting
    dtype: str = "auto"  # auto (float32 on CPU, bfloat16 on CUDA) | float32 | bfloat16 | float16
    # released (OpenVLA-format) folders: the ModelConfig YAML to build; None = the 7B compat preset
    model_config: str | None = None
    # a diagnostic: `empty` gives the agent no memory token at any step (its memory still records the frames),
    # so a paired comparison with a `none` run (python -m openfly_agent.eval.compare) says whether the memory
    # changes what the agent does; `none` = the model as trained
    memory_probe: str = C.MEMORY_PROBE_NONE

    def __post_init__(self) -> None:
        if self.memory_probe not in C.MEMORY_PROBES:
            raise ValueError(f"agent.memory_probe={self.memory_probe!r}: choose one of {C.MEMORY_PROBES}")
        if self.decode_rule is not None and self.decode_rule not in DECODE_RULES:
            raise ValueError(
                f"agent.decode_rule={self.decode_rule!r}: choose one of {DECODE_RULES} (or null)"
            )
        if self.dtype not in ("auto", "float32", "bfloat16", "float16"):
            raise ValueError(f"agent.dtype={self.dtype!r}: choose auto, float32, bfloat16 or float16")


@dataclass
class EvalConfig:
    """Closed-loop evaluation of one policy (plus baselines) on dataset splits.

    Outputs go to `<output_dir>/<policy>/` (episodes.jsonl, results.json, results.md, plots/, gifs/) and
    `<output_dir>/summary.md` (every policy side by side).
    """

    policy: str = "agent"  # agent | random | stop | forward | oracle | box_servo | agent_true_box
    # policy agent: our checkpoint folder (or its run folder / `last` pointer), an OpenVLA / OpenFly-Agent
    # folder, or a Hub id
    checkpoint: str | None = None
    # more policies run through the same runner after `policy`, e.g. --baselines=[random,stop]
    baselines: list[str] = field(default_factory=list)
    # the dataset (relative to the working directory): Annotation/*.json and traj/ parquet files
    dataset_root: str = "outputs/datasets/embedded-small"
    # splits to evaluate, e.g. --split=[test_seen,test_unseen]
    split: list[str] = field(default_factory=lambda: [C.SPLIT_TEST_SEEN, C.SPLIT_TEST_UNSEEN])
    # Label handling, as in training (take-off / landing trimmed: start at flight height, goal = the STOP
    # pose). Released-data parity: takeoff_landing=keep (start on the ground, goal = the landed point).
    reader: ReaderOptions = field(default_factory=ReaderOptions)
    max_episodes: int | None = None  # per split, N evenly spaced over the sorted ids (quick runs); None = all
    sim: SimSettings = field(default_factory=EmbeddedSimSettings)
    agent: AgentSettings = field(default_factory=AgentSettings)
    batch_size: int = 16  # episodes stepped in lockstep (the policy's batch)
    max_steps: int = C.MAX_EPISODE_STEPS  # actions per episode at most, STOP included
    profiles: list[str] = field(default_factory=lambda: list(PROFILE_NAMES))  # metric profiles reported
    oracle_mode: str = "auto"  # auto | replay | teleport (docs/EVAL.md)
    # the reflex reference policy on the true target box (embedded simulator only; docs/EVAL.md)
    box_servo: BoxServoSettings = field(default_factory=BoxServoSettings)
    # whose true box agent_true_box is fed: `final` (the route's last target) or `leg` (the target of the leg
    # the drone is on, moved on within the success radius of each leg's goal; chained routes, docs/EVAL.md)
    true_box: str = TRUE_BOX_FINAL
    # results: <output_dir>/summary.md and <output_dir>/<policy>/ (relative to the working directory)
    output_dir: str = "outputs/eval"
    plots: int = 6  # top-down plots per policy and split (evenly spaced over the episode ids)
    # episode ids to save as GIFs with the predicted box
    gif_episodes: list[str] = field(default_factory=list)
    seed: int = 0  # the random baseline's seed (per episode: seed + SHA-256 of the episode id)
    device: str = "auto"  # auto | cpu | cuda | cuda:<k>
    # CPU threads of the model (None: torch's default, one per core). 1 by default: the tiny model gains
    # nothing from intra-op threads, and with other work on the cores torch's default thrashed (20-50x slower
    # per step, docs/EVAL.md "Throughput")
    torch_threads: int | None = 1
    overwrite: bool = False  # discard existing logs in output_dir instead of resuming
    progress: bool = True  # draw a progress bar per policy and split

    def __post_init__(self) -> None:
        for name in [self.policy, *self.baselines]:
            if name not in POLICY_NAMES:
                raise ValueError(f"policy / baselines entry {name!r}: choose from {POLICY_NAMES}")
        if len({self.policy, *self.baselines}) != 1 + len(self.baselines):
            raise ValueError(f"policy {self.policy!r} and baselines {self.baselines} must not repeat a name")
        for name in set(TRUE_BOX_POLICIES) & {self.policy, *self.baselines}:
            if self.sim.type != SIM_EMBEDDED:
                raise ValueError(
                    f"{name} reads the true target box, which only the embedded simulator gives: drop it from "
                    f"--baselines with --sim.type={self.sim.type}"
                )
        if self.true_box not in TRUE_BOX_TARGETS:
            raise ValueError(f"true_box={self.true_box!r}: choose from {TRUE_BOX_TARGETS}")
        if self.true_box == TRUE_BOX_LEG and (
            "box_servo" in {self.policy, *self.baselines}
            or AGENT_TRUE_BOX not in {self.policy, *self.baselines}
        ):
            raise ValueError(
                "true_box=leg feeds agent_true_box the current leg's target box: add agent_true_box to --baselines "
                "and leave box_servo out (the reflex stops where its box is large, at the first leg's landmark)"
            )
        for name in set(AGENT_POLICIES) & {self.policy, *self.baselines}:
            if not self.checkpoint:
                raise ValueError(
                    f"policy {name!r} needs --checkpoint=<folder or Hub id> (or pick a baseline with --policy)"
                )
        for split in self.split:
            if split not in C.SPLITS:
                raise ValueError(f"split {split!r}: choose from {C.SPLITS}")
        if not self.split:
            raise ValueError("split is empty: pass e.g. --split=[test_seen,test_unseen]")
        for profile in self.profiles:
            if profile not in PROFILE_NAMES:
                raise ValueError(f"profile {profile!r}: choose from {PROFILE_NAMES}")
        if self.batch_size < 1 or self.max_steps < 1:
            raise ValueError(f"batch_size ({self.batch_size}) and max_steps ({self.max_steps}) must be >= 1")
        if self.max_episodes is not None and self.max_episodes < 1:
            raise ValueError(f"max_episodes={self.max_episodes} must be >= 1 (or null for all)")
        if self.oracle_mode not in ORACLE_MODES:
            raise ValueError(f"oracle_mode={self.oracle_mode!r}: choose from {ORACLE_MODES}")
        if self.torch_threads is not None and self.torch_threads < 1:
            raise ValueError(f"torch_threads={self.torch_threads} must be >= 1 (or null for torch's default)")
        if self.plots < 0:
            raise ValueError(f"plots={self.plots} must be >= 0")

    @property
    def policies(self) -> list[str]:
        """The policy, then the baselines, in run order."""
        return [self.policy, *self.baselines]

    def result_identity(self, policy: str) -> dict:
        """The settings that decide a policy's per-episode results (checked before resuming a log)."""
        identity = {
            "policy": policy,
            "dataset_root": self.dataset_root,
            "reader": [self.reader.takeoff_landing, self.reader.merged_forward_position],
            "max_steps": self.max_steps,
            **self.sim.result_identity(),
        }
        if policy in AGENT_POLICIES:
            identity.update(
                checkpoint=self.checkpoint,
                unnorm_key=self.agent.unnorm_key,
                decode_rule=self.agent.decode_rule,
            )
            if self.agent.memory_probe != C.MEMORY_PROBE_NONE:  # absent: the model as trained (older folders)
                identity["memory_probe"] = self.agent.memory_probe
        # absent: the final target (older logs)
        if policy == AGENT_TRUE_BOX and self.true_box != TRUE_BOX_FINAL:
            identity["true_box"] = self.true_box
        if policy == "random":
            identity["seed"] = self.seed
        if policy == "oracle":
            identity["oracle_mode"] = self.oracle_mode
        if policy == "box_servo":
            identity["box_servo"] = dataclasses.asdict(self.box_servo)
        return identity

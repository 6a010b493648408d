"""Typed configuration of the data toolchain (one nested dataclass per step), loaded from YAML by draccus.

Leaf module: imports only the standard library and `constants`, so run configs can compose it cheaply.
Field names follow the official `configs/env_*.yaml` where a counterpart exists (noted per field).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from openfly_agent import constants as C

# Work-unit index of a city's first validation route: its routes are units of their own (own seeds), after
# and apart from the `trajectories_per_scene` units of the other splits.
VAL_INDEX_BASE = 1_000_000
# whose box each frame of an episode holds (`render.box_target`)
BOX_TARGET_FINAL = "final"  # the route's last target, at every frame (the released data's labels)
BOX_TARGET_LEG = "leg"  # the target of the leg the frame belongs to (`leg_of_frame`)
BOX_TARGETS = (BOX_TARGET_FINAL, BOX_TARGET_LEG)


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


@dataclass
class MapConfig:
    """Point cloud -> voxel map and BEV map (`traj_map` + `seg_map` of the official env yaml)."""

    voxel_size_m: float = 2.0  # VoxelWidth
    dilate_radius_m: float = 3.0  # DilateRadius: obstacle inflation of the planning grid
    bounds: list[float] | None = None  # MapBound [xmin, xmax, ymin, ymax, zmin, zmax]; None = scene's
    elevation_m: float | None = None  # map_elevation (ground height); None = the scene's ground height
    min_height_thresh_m: float = 6.0  # min_height_thresh: points below elevation + this stay out of the BEV
    bev_voxel_size_m: float = 4.0  # seg_map.bev_voxel_size: BEV pixel size for landmark segmentation
    pcd_scale_ratio: float = 1.0  # point cloud units -> metres (multiplier)
    outlier_min_neighbors: int = 0  # drop points with fewer neighbours in their 3x3x3 voxel block; 0 = off

    def __post_init__(self) -> None:
        _check(self.voxel_size_m > 0, f"map.voxel_size_m must be > 0, got {self.voxel_size_m}")
        _check(self.dilate_radius_m >= 0, f"map.dilate_radius_m must be >= 0, got {self.dilate_radius_m}")
        _check(self.bev_voxel_size_m > 0, f"map.bev_voxel_size_m must be > 0, got {self.bev_voxel_size_m}")
        _check(self.pcd_scale_ratio > 0, f"map.pcd_scale_ratio must be > 0, got {self.pcd_scale_ratio}")
        if self.bounds is not None:
            b = self.bounds
            _check(
                len(b) == 6 and b[0] < b[1] and b[2] < b[3] and b[4] < b[5],
                f"map.bounds must be [xmin, xmax, ymin, ymax, zmin, zmax] with min < max, got {b}",
            )


@dataclass
class SegmentationConfig:
    """Landmark segmentation from the BEV map (official `seg_gen`)."""

    # "scene": the scene's landmark list (embedded city / official list); "segment": BEV contours
    source: str = "scene"
    erode_iterations: int = 2  # 3x3 erosions before contour extraction (official: 2)
    min_area_m2: float = 64.0  # contours smaller than this are dropped
    height_window_m: float = 5.0  # instance height = max z of points within +- this of the centroid

    def __post_init__(self) -> None:
        _check(
            self.source in ("scene", "segment"),
            f"segmentation.source must be 'scene' or 'segment', got {self.source!r}",
        )
        _check(self.erode_iterations >= 0, "segmentation.erode_iterations must be >= 0")


@dataclass
class RouteConfig:
    """Route sampling around landmarks (official `thread_params`)."""

    height_min_m: float = 5.0  # height_min: flight height above elevation + min_height_thresh
    height_max_m: float = 10.0  # height_max
    min_dist_m: float = 150.0  # min_dis: start ring inner radius around the landmark
    max_dist_m: float = 180.0  # max_dis: start ring outer radius
    min_goal_dist_m: float = (
        30.0  # straight start -> goal distance at least this (big footprints eat the ring)
    )
    landmark_top_slack_m: float = 15.0  # a landmark qualifies when its top is above flight height - this
    max_landmark_tries: int = 200  # landmarks tried per route before giving up
    max_start_tries: int = 20  # start candidates on the ring per landmark (official: 20)
    with_turn_prob: float = 0.0  # with_turn: probability that a route must be blocked in a straight line
    chain_prob: float = 0.0  # probability of a chained route, one that visits several landmarks in turn
    # [lo, hi]: a chained route visits U{lo..hi} landmarks (aimlandmark_nums; [2, 2]: always 2, no extra draw)
    chain_landmarks: list[int] = field(default_factory=lambda: [2, 2])
    chain_bearing_deg: list[float] = field(default_factory=lambda: [30.0, 150.0])  # each next leg turns this
    takeoff_landing_prob: float = 0.0  # add_takeoff_land: probability of -1 / -2 phases
    start_yaw_jitter_deg: float = 45.0  # start yaw = bearing to the goal +- U(jitter)

    def __post_init__(self) -> None:
        _check(0 <= self.height_min_m <= self.height_max_m, "route.height_min_m must be in [0, height_max_m]")
        _check(0 < self.min_dist_m <= self.max_dist_m, "route.min_dist_m must be in (0, max_dist_m]")
        _check(
            0 <= self.min_goal_dist_m < self.max_dist_m, "route.min_goal_dist_m must be in [0, max_dist_m)"
        )
        for name in ("with_turn_prob", "chain_prob", "takeoff_landing_prob"):
            value = getattr(self, name)
            _check(0.0 <= value <= 1.0, f"route.{name} must be a probability in [0, 1], got {value}")
        _check(
            len(self.chain_landmarks) == 2 and 2 <= self.chain_landmarks[0] <= self.chain_landmarks[1],
            f"route.chain_landmarks must be [lo, hi] with 2 <= lo <= hi, got {self.chain_landmarks}",
        )
        lo, hi = self.chain_bearing_deg
        _check(
            0 <= lo <= hi <= 180, f"route.chain_bearing_deg must be [lo, hi] within [0, 180], got {[lo, hi]}"
        )
        _check(self.max_landmark_tries > 0 and self.max_start_tries > 0, "route.max_*_tries must be > 0")


@dataclass
class PlannerConfig:
    """A* in the action space (3 m steps at 12 headings, 3 m climb / descend)."""

    turn_penalty: float = 2.0  # extra cost per 30 deg turn primitive
    vertical_penalty: float = 1.0  # extra cost per climb / descent primitive (prefer level flight)
    goal_tolerance_m: float = 3.1  # search stops within this distance of the goal (official 3.1)
    max_expansions: int = 20000  # bounded search: the route is discarded (and counted) beyond this
    key_resolution_m: float = 1.5  # visited-state key = position rounded to this grid (official: 1 m)
    # 1 = (near-)admissible distance + turns heuristic; 1.5 = weighted A*: ~6x fewer expansions, paths
    # ~0.3 percent longer with ~20 percent more turns on a 1 km embedded city (measured, docs/TOOLCHAIN.md)
    heuristic_weight: float = 1.5

    def __post_init__(self) -> None:
        _check(self.turn_penalty >= 0 and self.vertical_penalty >= 0, "planner penalties must be >= 0")
        _check(
            self.goal_tolerance_m >= C.STEP_METERS / 2,
            "planner.goal_tolerance_m must be >= 1.5 (half a step)",
        )
        _check(self.max_expansions > 0, "planner.max_expansions must be > 0")
        _check(self.key_resolution_m > 0, "planner.key_resolution_m must be > 0")
        _check(self.heuristic_weight >= 1.0, "planner.heuristic_weight must be >= 1")


@dataclass
class CategoryConfig:
    """`{low,medium,high}_{short,average,long}` by flight height above ground and path length."""

    height_bins_m: list[float] = field(default_factory=lambda: [30.0, 60.0])  # low < a <= medium < b
    length_bins_m: list[float] = field(default_factory=lambda: [100.0, 200.0])  # short < a <= average < b

    def __post_init__(self) -> None:
        for name in ("height_bins_m", "length_bins_m"):
            bins = getattr(self, name)
            _check(len(bins) == 2 and bins[0] < bins[1], f"categories.{name} must be two increasing numbers")


@dataclass
class RenderConfig:
    """Frames of every kept pose, rendered by a Simulator."""

    width: int = 128
    height: int = 128
    min_box_pixels: int = 0  # boxes smaller than this many pixels (w * h in pixels) count as not visible
    # whose box (and visibility) each frame's label holds: `final`, the route's last target at every frame, or
    # `leg`, the target of the leg the frame belongs to, so that on a chained route the box is the landmark the
    # expert is flying to (DAgger's recovery episodes keep `final`)
    box_target: str = BOX_TARGET_FINAL

    def __post_init__(self) -> None:
        _check(self.width >= 16 and self.height >= 16, "render.width / height must be >= 16 pixels")
        _check(self.min_box_pixels >= 0, f"render.min_box_pixels must be >= 0, got {self.min_box_pixels}")
        _check(
            self.box_target in BOX_TARGETS,
            f"render.box_target must be one of {BOX_TARGETS}, got {self.box_target!r}",
        )


@dataclass
class VLMConfig:
    """OpenAI-compatible chat completions endpoint (`/v1/chat/completions`)."""

    base_url: str = "https://api.openai.com/v1"
    model: str = "gpt-4o"
    api_key_env: str = "OPENAI_API_KEY"  # name of the environment variable holding the key (never logged)
    concurrency: int = 10  # simultaneous requests (official: 10)
    max_retries: int = 3  # retries per request after the first try (official: 3)
    backoff_s: float = 1.0  # first retry delay; doubles each retry
    timeout_s: float = 60.0
    temperature: float = 0.7
    max_tokens: int = 300
    image_size: int = 224  # frames are resized to this (longest side) before base64 encoding

    def __post_init__(self) -> None:
        _check(
            self.base_url.startswith(("http://", "https://")),
            f"vlm.base_url must be http(s)://..., got {self.base_url!r}",
        )
        _check(self.concurrency >= 1, "vlm.concurrency must be >= 1")
        _check(
            self.max_retries >= 0 and self.backoff_s >= 0 and self.timeout_s > 0,
            "vlm retry/timeout must be >= 0",
        )


@dataclass
class InstructionConfig:
    """How the instruction of each trajectory is written."""

    backend: str = "template"  # "template" (offline, default) | "vlm" (OpenAI-compatible API)
    vlm: VLMConfig = field(default_factory=VLMConfig)
    min_box_area: float = 0.002  # a landmark is 'seen' in a frame when its box covers this image fraction
    mention_distance: bool = True  # template: say distances of long straight legs ("about 60 meters")
    # jogs (a forward run shorter than this between two turns) fold into one net turn; 0 = a clause per
    # action transition, exactly as the paper splits
    merge_short_m: float = 9.0
    # a leg target whose leg ends in a climb, or in the clause of the next target, is named by the next
    # clause that can name it (so a chained route's instruction names every target, in order); false: it is
    # named only where its leg ends (embedded-small's instructions)
    name_every_target: bool = False
    # template: the clause after each leg's end starts "after passing <the target just reached>", and that
    # target is the clause's deciding landmark in the visibility statistics; false: embedded-small's instructions
    name_passed_landmark: bool = False

    def __post_init__(self) -> None:
        _check(self.merge_short_m >= 0, "instructions.merge_short_m must be >= 0")
        _check(
            not self.name_passed_landmark or self.backend == "template",
            "instructions.name_passed_landmark is a template option; the vlm backend writes its own clauses",
        )
        _check(
            self.backend in ("template", "vlm"),
            f"instructions.backend must be 'template' or 'vlm', got {self.backend!r}",
        )


@dataclass
class FilterConfig:
    """Quality filters of the paper."""

    min_actions: int = 2
    max_actions: int = 150
    min_frame_std: float = 3.0  # a frame whose pixel std is below this (uniform colour) is damaged
    max_dominant_fraction: float = 0.98  # ... or whose most common colour covers more than this fraction
    tree_height_m: float | None = None  # no navigation pose below ground + this; None = scene's tallest tree

    def __post_init__(self) -> None:
        _check(1 <= self.min_actions <= self.max_actions, "filters: need 1 <= min_actions <= max_actions")
        _check(0 < self.max_dominant_fraction <= 1, "filters.max_dominant_fraction must be in (0, 1]")


@dataclass
class DaggerConfig:
    """Recovery episodes: roll out a noisy expert (or a policy), relabel visited states with the A* expert."""

    episodes_per_scene: int = 0  # train scenes only; 0 = off
    noise_prob: float = 0.3  # per step, a random action replaces the expert's
    max_policy_steps: int = 30  # policy steps before the expert takes over to the goal
    max_steps: int = 150

    def __post_init__(self) -> None:
        _check(self.episodes_per_scene >= 0, "dagger.episodes_per_scene must be >= 0")
        _check(0.0 <= self.noise_prob <= 1.0, "dagger.noise_prob must be in [0, 1]")
        _check(0 < self.max_policy_steps <= self.max_steps, "dagger: need 0 < max_policy_steps <= max_steps")


@dataclass
class SceneConfig:
    """Which scenes are generated and how they split (unseen and validation seeds are never used in train).

    The `val` split holds route attempts of the train cities beyond `trajectories_per_scene` (work units of
    their own, numbered from `VAL_INDEX_BASE`, so the other splits do not change) and every route of the
    validation cities `val_seeds`. Off by default; the shipped configs turn it on (docs/TOOLCHAIN.md, "Splits").
    """

    train_seeds: list[int] = field(default_factory=lambda: [0, 1])
    unseen_seeds: list[int] = field(default_factory=lambda: [100])
    test_seen_fraction: float = 0.1  # of the trajectories of train scenes
    trajectories_per_scene: int = 100  # route attempts per scene (work units); rejected ones are counted
    val_seen_per_scene: int = 0  # val: route attempts per train city, kept out of training
    val_seeds: list[int] = field(default_factory=list)  # val: validation cities, used for no other split
    val_unseen_per_scene: int = 0  # val: route attempts per validation city
    city_size_m: float = 1000.0  # embedded city size
    city_buildings: int | None = None  # None = the city generator's default
    point_spacing_m: float = 2.0  # point cloud sampling of the embedded city

    def __post_init__(self) -> None:
        for name in ("train_seeds", "unseen_seeds"):
            for seed in getattr(self, name):
                _check(seed >= 0, f"scenes.{name}: a city seed is an integer >= 0, got {seed}")
        overlap = set(self.train_seeds) & set(self.unseen_seeds)
        _check(
            not overlap, f"scenes: unseen_seeds must not be used in train_seeds (both hold {sorted(overlap)})"
        )
        _check(len(set(self.train_seeds)) == len(self.train_seeds), "scenes.train_seeds has duplicates")
        reused = set(self.val_seeds) & (set(self.train_seeds) | set(self.unseen_seeds))
        _check(
            not reused,
            f"scenes: val_seeds must not be used in train_seeds or unseen_seeds (both hold {sorted(reused)})",
        )
        _check(len(set(self.val_seeds)) == len(self.val_seeds), "scenes.val_seeds has duplicates")
        _check(0.0 <= self.test_seen_fraction < 1.0, "scenes.test_seen_fraction must be in [0, 1)")
        _check(len(set(self.unseen_seeds)) == len(self.unseen_seeds), "scenes.unseen_seeds has duplicates")
        _check(
            1 <= self.trajectories_per_scene < VAL_INDEX_BASE,
            f"scenes.trajectories_per_scene must be in [1, {VAL_INDEX_BASE})",
        )
        _check(
            self.val_seen_per_scene >= 0 and self.val_unseen_per_scene >= 0,
            "scenes.val_seen_per_scene and scenes.val_unseen_per_scene must be >= 0",
        )
        _check(
            self.val_unseen_per_scene >= 1 or not self.val_seeds,
            "scenes.val_seeds needs scenes.val_unseen_per_scene >= 1 (route attempts per validation city)",
        )
        _check(self.city_size_m > 0, f"scenes.city_size_m must be > 0, got {self.city_size_m}")
        _check(
            self.city_buildings is None or self.city_buildings >= 1,
            f"scenes.city_buildings must be >= 1 (or null: the generator's default), got {self.city_buildings}",
        )
        _check(self.point_spacing_m > 0, f"scenes.point_spacing_m must be > 0, got {self.point_spacing_m}")


@dataclass
class GenerateConfig:
    """`python -m openfly_agent.toolchain generate --config_path configs/toolchain/<name>.yaml`."""

    output_dir: str = (
        "outputs/datasets/embedded-small"  # the dataset root (relative to the working directory)
    )
    seed: int = 0  # base of every per-unit seed
    workers: int = 2  # processes (spawn); 0 = run in this process
    shard: str = "0/1"  # "i/N": this machine generates the scenes whose position in the scene list is i mod N
    scenes: SceneConfig = field(default_factory=SceneConfig)
    map: MapConfig = field(default_factory=MapConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    route: RouteConfig = field(default_factory=RouteConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    categories: CategoryConfig = field(default_factory=CategoryConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    instructions: InstructionConfig = field(default_factory=InstructionConfig)
    filters: FilterConfig = field(default_factory=FilterConfig)
    dagger: DaggerConfig = field(default_factory=DaggerConfig)
    instruction_batch: int = 64  # trajectories whose instructions are generated together (VLM concurrency)
    plots: bool = True  # write meta/toolchain/summary.png
    # discard the dataset in output_dir (Annotation/, traj/, meta/) and generate anew; without it a rerun
    # resumes, and a rerun with other data settings is refused
    overwrite: bool = False

    def __post_init__(self) -> None:
        _check(self.seed >= 0, f"seed must be >= 0 (the base of every per-unit seed), got {self.seed}")
        _check(self.workers >= 0, "workers must be >= 0")
        parse_shard(self.shard)
        _check(self.instruction_batch >= 1, "instruction_batch must be >= 1")
        _check(
            self.route.min_dist_m > self.planner.goal_tolerance_m,
            "route.min_dist_m must exceed planner.goal_tolerance_m",
        )


@dataclass
class DaggerRoundConfig:
    """One DAgger round with the trained agent in the loop (toolchain/dagger_rounds.py).

    Rollouts start from train episodes of `source_root` (start pose, instruction, goal); the planning maps and
    frame size come from its saved toolchain config. The written dataset joins the training data.
    """

    source_root: str = "outputs/datasets/embedded-small"  # dataset whose train episodes the agent flies
    output_dir: str = "outputs/datasets/dagger-r1"  # where the round's rollouts are written (a new dataset)
    round_name: str = "r1"  # part of the written episode ids
    episodes: int = 400  # rollouts (train episodes drawn without replacement)
    expert_mix: float = 0.0  # probability that the expert's action is flown instead of the agent's
    max_policy_steps: int = 60  # agent-flown states at most; then the expert flies to the goal
    max_steps: int = 150  # states at most (a rollout without a STOP by then is dropped)
    # the expert labels STOP at every state within this 3-D distance of the goal (0: only where A* stops,
    # within planner.goal_tolerance_m). Half the 20-m success radius leaves a margin for a late STOP.
    stop_radius_m: float = 10.0
    num_envs: int = 16  # rollouts in lockstep (the agent's batch)
    seed: int = 0  # seed of the episode draw and of expert_mix

    def __post_init__(self) -> None:
        _check(self.episodes >= 1, "dagger round: episodes must be >= 1")
        _check(0.0 <= self.expert_mix <= 1.0, "dagger round: expert_mix must be in [0, 1]")
        _check(
            0 <= self.max_policy_steps <= self.max_steps,
            "dagger round: need 0 <= max_policy_steps <= max_steps",
        )
        _check(self.num_envs >= 1, "dagger round: num_envs must be >= 1")
        _check(
            0.0 <= self.stop_radius_m < C.SUCCESS_RADIUS_M,
            f"dagger round: stop_radius_m must be in [0, {C.SUCCESS_RADIUS_M}) (the success radius)",
        )


@dataclass
class GroundingDataConfig:
    """`python -m openfly_agent.toolchain grounding`: referring expressions on rendered frames of a dataset's cities.

    The frame size and city parameters come from the source dataset's toolchain config, so the grounding
    frames look exactly like the navigation frames.
    """

    # navigation dataset whose trajectory poses are rendered
    source_root: str = "outputs/datasets/embedded-small"
    output_dir: str = "outputs/datasets/grounding-small"  # where the grounding dataset is written
    splits: list[str] = field(default_factory=lambda: [C.SPLIT_TRAIN])  # source splits (test: eval sets)
    yaw_copies: int = 1  # extra views per pose, its yaw turned by a random angle in +- yaw_jitter_deg
    yaw_jitter_deg: float = 60.0  # largest yaw offset of the extra views (degrees)
    min_box_area: float = 0.002  # a landmark is described when its box covers this fraction of the frame
    frames_per_part: int = 2048  # rows per parquet part
    seed: int = 0  # seed of the yaw offsets and of the optional words of the expressions

    def __post_init__(self) -> None:
        for split in self.splits:
            _check(split in C.SPLITS, f"grounding splits: {split!r} is not one of {C.SPLITS}")
        _check(self.yaw_copies >= 0, "yaw_copies must be >= 0")
        _check(0.0 <= self.min_box_area < 1.0, "min_box_area must be in [0, 1)")
        _check(self.frames_per_part >= 1, "frames_per_part must be >= 1")


def parse_shard(shard: str) -> tuple[int, int]:
    """'i/N' -> (i, N) with 0 <= i < N."""
    try:
        index, count = (int(part) for part in str(shard).split("/"))
    except ValueError:
        raise ValueError(f"shard must look like 'i/N' (e.g. '0/4'), got {shard!r}") from None
    _check(count >= 1 and 0 <= index < count, f"shard {shard!r}: need 0 <= i < N")
    return index, count

"""Readers for the official real-scene inputs: landmark lists (`seg_map/*.jsonl`) and `env_*.yaml` configs.

Both are turned into our types (`Landmark`, `SceneBounds`, `RealSceneConfig`) in the world frame of
docs/CONVENTIONS.md; unit conversions follow docs/OFFICIAL_OPENFLY.md sections 2 and 7.3.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from openfly_agent.sim.scene import Landmark, SceneBounds
from openfly_agent.utils.errors import RecordError

ENGINE_UE = "ue"
ENGINE_AIRSIM = "airsim"
ENGINE_GS = "gs"
_ENGINE_PREFIXES = {"env_ue_": ENGINE_UE, "env_airsim_": ENGINE_AIRSIM, "env_gs_": ENGINE_GS}

UE_CM_PER_M = 100.0  # UE landmark files: centimetres, left-handed (y points the other way)

# pcd_scale_ratio of each 3DGS scene (point cloud / render units -> unified metres), from its env yaml.
# The official eval divides every GS pose by 5.15 (nwpu02's ratio), right for nwpu02 only.
GS_SCALE_RATIOS: dict[str, float] = {
    "env_gs_ecust": 5.6,
    "env_gs_nwpu01": 6.65,
    "env_gs_nwpu02": 5.15,
    "env_gs_sjtu01": 5.42,
    "env_gs_sjtu02": 4.75,
}
OFFICIAL_EVAL_GS_SCALE = 5.15

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_LANDMARK_FILENAME = re.compile(rf"^X=(?P<x>{_NUMBER})Y=(?P<y>{_NUMBER})Z=(?P<z>{_NUMBER})\.png$")
_LANDMARK_TEXT_FIELDS = ("type", "color", "size", "shape", "feature")


def engine_of(env: str) -> str:
    """ "ue", "airsim" or "gs" from an official scene name such as `env_airsim_16`."""
    for prefix, engine in _ENGINE_PREFIXES.items():
        if env.startswith(prefix):
            return engine
    raise ValueError(
        f"unknown engine for scene {env!r}: expected a name starting with {sorted(_ENGINE_PREFIXES)}"
    )


def default_pcd_scale_ratio(env: str) -> float:
    """The point-cloud -> metres ratio of an official scene: 1 for AirSim, the table for 3DGS, 100 for UE."""
    engine = engine_of(env)
    if engine == ENGINE_AIRSIM:
        return 1.0
    if engine == ENGINE_UE:
        return UE_CM_PER_M
    if env not in GS_SCALE_RATIOS:
        raise ValueError(
            f"no known pcd_scale_ratio for 3DGS scene {env!r} (known: {sorted(GS_SCALE_RATIOS)}); "
            "pass it explicitly, e.g. from read_scene_config(<env yaml>).pcd_scale_ratio"
        )
    return GS_SCALE_RATIOS[env]


def _env_from_landmark_path(path: Path) -> str:
    stem = path.stem
    return stem[len("seg_map_") :] if stem.startswith("seg_map_") else stem


def landmark_position(x: float, y: float, z: float, engine: str, pcd_scale_ratio: float) -> tuple[float, ...]:
    """A landmark-file position -> world metres: UE cm left-handed -> /100 with y negated; else * ratio."""
    if engine == ENGINE_UE:
        return (x / UE_CM_PER_M, -y / UE_CM_PER_M, z / UE_CM_PER_M)
    return (x * pcd_scale_ratio, y * pcd_scale_ratio, z * pcd_scale_ratio)


def _parse_landmark_line(text: str, path: Path, line: int) -> tuple[dict, tuple[float, float, float]]:
    try:
        record = json.loads(text)
    except json.JSONDecodeError as err:
        raise RecordError(path, line, "<json>", f"not valid JSON ({err.msg} at column {err.colno})") from None
    if not isinstance(record, dict):
        raise RecordError(path, line, "<json>", f"expected a JSON object, got {type(record).__name__}")
    for name in (*_LANDMARK_TEXT_FIELDS, "filename"):
        if not isinstance(record.get(name), str):
            problem = "missing" if name not in record else f"expected a string, got {record[name]!r}"
            raise RecordError(path, line, name, problem)
    match = _LANDMARK_FILENAME.match(record["filename"])
    if match is None:
        raise RecordError(
            path, line, "filename", f"{record['filename']!r} does not match 'X=<x>Y=<y>Z=<z>.png'"
        )
    return record, (float(match["x"]), float(match["y"]), float(match["z"]))


def read_landmark_list(
    path: str | Path, env: str | None = None, pcd_scale_ratio: float | None = None
) -> list[Landmark]:
    """Read an official landmark list (one JSON object per line, position encoded in `filename`).

    Args:
        path: `seg_map_<env>.jsonl` or `<env>.jsonl`.
        env: scene name; by default taken from the file name. Its prefix selects the engine.
        pcd_scale_ratio: multiplier for AirSim / 3DGS files (default: `default_pcd_scale_ratio(env)`);
            UE files are always centimetres (/100, y negated) and ignore it.

    Returns:
        Landmarks with ids `<env>/<record index>`, positions in world metres (z = the file's Z, the
        roof height for BEV-segmented scenes), zero extent, and `attributes` holding the file name,
        source line and engine. Placeholder attribute values ("test") are kept as they are.
    """
    path = Path(path)
    env = env or _env_from_landmark_path(path)
    engine = engine_of(env)
    ratio = default_pcd_scale_ratio(env) if pcd_scale_ratio is None else float(pcd_scale_ratio)
    if not ratio > 0:
        raise ValueError(f"{path}: pcd_scale_ratio must be > 0, got {ratio}")
    landmarks: list[Landmark] = []
    with path.open(encoding="utf-8") as handle:
        for line_number, text in enumerate(handle, start=1):
            if not text.strip():
                continue
            record, (x, y, z) = _parse_landmark_line(text, path, line_number)
            landmarks.append(
                Landmark(
                    landmark_id=f"{env}/{len(landmarks)}",
                    type=record["type"],
                    color=record["color"],
                    size=record["size"],
                    shape=record["shape"],
                    feature=record["feature"],
                    position=landmark_position(x, y, z, engine, ratio),
                    attributes={"filename": record["filename"], "line": line_number, "engine": engine},
                )
            )
    return landmarks


@dataclass(frozen=True)
class ThreadParams:
    """One `thread_params` entry of an env yaml (a data-generation worker); distances in metres."""

    name: str
    nums: int  # trajectories to generate
    min_dis: float  # start distance ring around the landmark
    max_dis: float
    height_min: float  # flight height above elevation + min_height_thresh
    height_max: float
    aim_port: int  # bridge TCP port
    listen_port: int
    sim_ip: str
    sim_port: int
    aimlandmark_nums: int  # landmarks per route
    add_takeoff_land: bool
    with_turn: bool
    extra: dict = field(default_factory=dict)  # keys we do not interpret


@dataclass(frozen=True)
class RealSceneConfig:
    """An official `configs/env_*.yaml` (docs/OFFICIAL_OPENFLY.md section 7.1)."""

    env: str
    data_type: str
    freq: float  # pose send rate, Hz
    dilate_radius: float  # traj_map.DilateRadius, metres
    voxel_width: float  # traj_map.VoxelWidth, metres
    map_bound: SceneBounds  # traj_map.MapBound as written (zmin is replaced by map_elevation when planning)
    lidar_delta: tuple[float, float, float]
    pcd_scale_ratio: float  # point cloud -> unified metres
    traj_scale_ratio: float  # unified -> simulator units
    map_elevation: float
    min_height_thresh: float
    bev_voxel_size: float  # seg_map.bev_voxel_size, metres
    thread_params: tuple[ThreadParams, ...]
    source: str = ""

    @property
    def engine(self) -> str:
        return engine_of(self.env)

    @property
    def planning_bounds(self) -> SceneBounds:
        """`map_bound` with zmin replaced by `map_elevation`, as the trajectory generator uses it."""
        b = self.map_bound
        return SceneBounds(b.xmin, b.xmax, b.ymin, b.ymax, self.map_elevation, b.zmax)


class _YamlFields:
    """Typed access to nested YAML keys; errors name the file, the line and the dotted field."""

    def __init__(self, path: Path, text: str):
        import yaml

        self.path = path
        try:
            self.root_node = yaml.compose(text, Loader=yaml.SafeLoader)
            self.data = yaml.safe_load(text)
        except yaml.YAMLError as err:
            mark = getattr(err, "problem_mark", None)
            raise RecordError(
                path, mark.line + 1 if mark else None, "<yaml>", f"not valid YAML: {err}"
            ) from None
        if not isinstance(self.data, dict):
            raise RecordError(path, 1, "<yaml>", "expected a mapping at the top level")

    def line_of(self, keys: tuple) -> int | None:
        import yaml

        node, line = self.root_node, None
        for key in keys:
            if isinstance(node, yaml.MappingNode):
                match = next(((k, v) for k, v in node.value if k.value == key), None)
                if match is None:
                    return line
                line, node = match[0].start_mark.line + 1, match[1]
            elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
                node = node.value[key]
                line = node.start_mark.line + 1
            else:
                return line
        return line

    def error(self, keys: tuple, problem: str) -> RecordError:
        dotted = ".".join(f"[{k}]" if isinstance(k, int) else str(k) for k in keys).replace(".[", "[")
        return RecordError(self.path, self.line_of(keys), dotted, problem)

    def get(self, keys: tuple, convert: Callable[[Any], Any], expected: str) -> Any:
        value: Any = self.data
        for depth, key in enumerate(keys):
            container_ok = isinstance(value, dict) if isinstance(key, str) else isinstance(value, list)
            if (
                not container_ok
                or (isinstance(key, str) and key not in value)
                or (isinstance(key, int) and key >= len(value))
            ):
                raise self.error(keys[: depth + 1], "missing")
            value = value[key]
        try:
            return convert(value)
        except (TypeError, ValueError):
            raise self.error(keys, f"expected {expected}, got {value!r}") from None


def _number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(value)
    return float(value)


def _integer(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(value)
    return value


def _boolean(value: Any) -> bool:
    if not isinstance(value, bool):
        raise TypeError(value)
    return value


def _string(value: Any) -> str:
    if not isinstance(value, str):
        raise TypeError(value)
    return value


def _numbers(count: int) -> Callable[[Any], tuple[float, ...]]:
    def convert(value: Any) -> tuple[float, ...]:
        if not isinstance(value, list) or len(value) != count:
            raise TypeError(value)
        return tuple(_number(v) for v in value)

    return convert


_THREAD_FIELDS: dict[str, tuple[Callable[[Any], Any], str]] = {
    "name": (_string, "a string"),
    "nums": (_integer, "an integer"),
    "min_dis": (_number, "a number"),
    "max_dis": (_number, "a number"),
    "height_min": (_number, "a number"),
    "height_max": (_number, "a number"),
    "aim_port": (_integer, "an integer port"),
    "listen_port": (_integer, "an integer port"),
    "sim_ip": (_string, "a string"),
    "sim_port": (_integer, "an integer port"),
    "aimlandmark_nums": (_integer, "an integer"),
    "add_takeoff_land": (_boolean, "true or false"),
    "with_turn": (_boolean, "true or false"),
}


def _read_threads(fields: _YamlFields) -> tuple[ThreadParams, ...]:
    entries = fields.data.get("thread_params")
    if not isinstance(entries, list) or not entries:
        problem = (
            "missing" if entries is None else f"expected a non-empty list of worker entries, got {entries!r}"
        )
        raise fields.error(("thread_params",), problem)
    threads = []
    for index, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise fields.error(("thread_params", index), f"expected a mapping, got {entry!r}")
        values = {
            name: fields.get(("thread_params", index, name), convert, expected)
            for name, (convert, expected) in _THREAD_FIELDS.items()
        }
        extra = {k: v for k, v in entry.items() if k not in _THREAD_FIELDS}
        threads.append(ThreadParams(**values, extra=extra))
    return tuple(threads)


def read_scene_config(path: str | Path) -> RealSceneConfig:
    """Read an official `env_*.yaml` into a `RealSceneConfig`.

    Raises:
        RecordError: a missing or mistyped field (file, line and dotted field in the message), or a
            `datagen.env` that differs from the file name (the official tools require them equal).
    """
    path = Path(path)
    fields = _YamlFields(path, path.read_text(encoding="utf-8"))
    env = fields.get(("datagen", "env"), _string, "a string")
    if env != path.stem:
        raise fields.error(("datagen", "env"), f"{env!r} must equal the file name {path.stem!r}")
    engine_of(env)  # unknown prefixes fail here, with the expected ones in the message
    bound = fields.get(("traj_map", "MapBound"), _numbers(6), "[xmin, xmax, ymin, ymax, zmin, zmax]")
    if not (bound[0] < bound[1] and bound[2] < bound[3] and bound[4] < bound[5]):
        raise fields.error(("traj_map", "MapBound"), f"expected min < max on each axis, got {list(bound)}")
    positive = ("DilateRadius", "VoxelWidth", "pcd_scale_ratio", "traj_scale_ratio")
    traj_map = {name: fields.get(("traj_map", name), _number, "a number") for name in positive}
    for name in positive:
        if not traj_map[name] > 0:
            raise fields.error(("traj_map", name), f"expected a positive number, got {traj_map[name]}")
    return RealSceneConfig(
        env=env,
        data_type=fields.get(("datagen", "data_type"), _string, "a string"),
        freq=fields.get(("datagen", "freq"), _number, "a number (Hz)"),
        dilate_radius=traj_map["DilateRadius"],
        voxel_width=traj_map["VoxelWidth"],
        map_bound=SceneBounds(*bound),
        lidar_delta=fields.get(("traj_map", "LidarDelta"), _numbers(3), "[dx, dy, dz]"),
        pcd_scale_ratio=traj_map["pcd_scale_ratio"],
        traj_scale_ratio=traj_map["traj_scale_ratio"],
        map_elevation=fields.get(("traj_map", "map_elevation"), _number, "a number"),
        min_height_thresh=fields.get(("traj_map", "min_height_thresh"), _number, "a number"),
        bev_voxel_size=fields.get(("seg_map", "bev_voxel_size"), _number, "a number"),
        thread_params=_read_threads(fields),
        source=str(path),
    )

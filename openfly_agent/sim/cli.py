"""Command line for the embedded city: render frames (with boxes) and export point clouds / landmark lists.

python -m openfly_agent.sim.cli render --seed=0 --pose=[-200,-100,40,0.3] --pitch=-45 --out=frame.png --boxes
python -m openfly_agent.sim.cli export --seed=0 --out=city.ply [--spacing=2] [--ascii] [--ground]
python -m openfly_agent.sim.cli landmarks --seed=0 --out=landmarks.jsonl
"""

from __future__ import annotations

import json
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from openfly_agent.sim.city import CityConfig, generate_city, scene_id_of
from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator
from openfly_agent.sim.pointcloud import write_points
from openfly_agent.utils.cli_help import choose_command, command_help, commands_usage, wants_help
from openfly_agent.utils.config import parse_config
from openfly_agent.utils.errors import root_cause
from openfly_agent.utils.geometry import Pose
from openfly_agent.utils.logging_utils import setup_logging

logger = logging.getLogger(__name__)

PROG = "python -m openfly_agent.sim.cli"
EXIT_BAD_INPUT = 2


@dataclass
class CityOutputConfig:
    """The city a command writes from, and the file it writes."""

    seed: int = 0  # city seed (scene id embedded-<seed>)
    size_m: float = 1000.0  # city side in metres
    out: str = ""  # file to write (required)

    def __post_init__(self) -> None:
        if not self.out:
            raise ValueError("--out is required: the file to write")


@dataclass
class RenderConfig(CityOutputConfig):
    """`render`: one frame of a city (PNG), optionally with its landmark boxes."""

    # camera [x, y, z, yaw]: position in metres and yaw in radians (counter-clockwise from +x)
    pose: list[float] = field(default_factory=lambda: [0.0, 0.0, 60.0, 0.0])
    pitch: float = 0.0  # degrees, negative = down
    width: int = 224  # frame width in pixels
    height: int = 224  # frame height in pixels
    boxes: bool = False  # draw the landmark boxes

    def __post_init__(self) -> None:
        super().__post_init__()
        if len(self.pose) != 4:
            raise ValueError(f"--pose takes 4 numbers [x,y,z,yaw], got {len(self.pose)}")


@dataclass
class ExportConfig(CityOutputConfig):
    """`export`: a city's surface as a point cloud (.ply / .pcd)."""

    spacing: float = 2.0  # metres between surface samples
    ascii: bool = False  # ASCII instead of binary
    ground: bool = False  # also sample the ground plane


@dataclass
class LandmarksConfig(CityOutputConfig):
    """`landmarks`: a city's landmark list (JSON lines)."""


def draw_boxes(rgb: np.ndarray, boxes: dict[str, np.ndarray], color=(255, 255, 0)) -> np.ndarray:
    """A copy of `rgb` (H, W, 3) with each (cx, cy, w, h) box outlined and labelled."""
    import cv2

    out = np.ascontiguousarray(rgb[..., ::-1])  # BGR for OpenCV
    h, w = rgb.shape[:2]
    for name, (cx, cy, bw, bh) in boxes.items():
        p0 = (int(round((cx - bw / 2) * w)), int(round((cy - bh / 2) * h)))
        p1 = (int(round((cx + bw / 2) * w)) - 1, int(round((cy + bh / 2) * h)) - 1)
        cv2.rectangle(out, p0, p1, color[::-1], 1)
        cv2.putText(out, name, (p0[0] + 1, p0[1] + 9), cv2.FONT_HERSHEY_PLAIN, 0.6, color[::-1], 1)
    return out[..., ::-1]


def _render(cfg: RenderConfig) -> None:
    import cv2

    sim_cfg = EmbeddedSimConfig(width=cfg.width, height=cfg.height, city=CityConfig(size_m=cfg.size_m))
    with EmbeddedSimulator(sim_cfg) as sim:
        obs = sim.render(scene_id_of(cfg.seed), Pose(*cfg.pose), cfg.pitch)
    rgb = draw_boxes(obs.rgb, obs.boxes) if cfg.boxes else obs.rgb
    cv2.imwrite(cfg.out, rgb[..., ::-1])
    print(f"wrote {cfg.out}: {len(obs.boxes)} landmark boxes")


def _export(cfg: ExportConfig) -> None:
    city = generate_city(cfg.seed, CityConfig(size_m=cfg.size_m))
    points = city.point_cloud(cfg.spacing, include_ground=cfg.ground)
    write_points(Path(cfg.out), points, binary=not cfg.ascii)
    print(f"wrote {cfg.out}: {len(points)} points of {city.scene_id}")


def _landmarks(cfg: LandmarksConfig) -> None:
    city = generate_city(cfg.seed, CityConfig(size_m=cfg.size_m))
    with open(cfg.out, "w") as f:
        for lm in city.landmarks:
            record = {k: getattr(lm, k) for k in ("landmark_id", "type", "color", "size", "shape", "feature")}
            record.update(position=list(lm.position), extent=list(lm.extent), description=lm.description())
            f.write(json.dumps(record) + "\n")
    print(f"wrote {cfg.out}: {len(city.landmarks)} landmarks of {city.scene_id}")


COMMANDS = {  # name: (config class, what it does, how it runs, example)
    "render": (
        RenderConfig,
        "render one frame of a city (PNG), optionally with its landmark boxes",
        _render,
        f"{PROG} render --seed=0 --pose=[-200,-100,40,0.3] --pitch=-45 --out=frame.png --boxes",
    ),
    "export": (
        ExportConfig,
        "export a city's surface as a point cloud (.ply / .pcd)",
        _export,
        f"{PROG} export --seed=0 --out=city.ply --spacing=2",
    ),
    "landmarks": (
        LandmarksConfig,
        "write a city's landmark list (JSON lines)",
        _landmarks,
        f"{PROG} landmarks --seed=0 --out=landmarks.jsonl",
    ),
}


def usage() -> str:
    """The help of `python -m openfly_agent.sim.cli --help` (each command's own: `<command> --help`)."""
    commands = {name: text for name, (_, text, _, _) in COMMANDS.items()}
    examples = [example for _, _, _, example in COMMANDS.values()]
    return commands_usage(PROG, __doc__.split("\n\n")[0], commands, examples)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (2 with one line on stderr for bad input)."""
    chosen = choose_command(list(sys.argv[1:] if argv is None else argv), list(COMMANDS), PROG, usage())
    if isinstance(chosen, int):
        return chosen
    command, args = chosen
    config_class, description, run, example = COMMANDS[command]
    if wants_help(args):
        print(command_help(config_class, args, f"{PROG} {command}", description, [example]), end="")
        return 0
    try:
        cfg = parse_config(config_class, args)
    except Exception as err:  # an unknown option (did you mean ...), a bad value, a missing --out
        from draccus.utils import DraccusException

        if not isinstance(err, (ValueError, DraccusException)):
            raise
        print(f"{PROG} {command}: {root_cause(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    setup_logging()
    run(cfg)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Command line for the embedded city: render frames (with boxes) and export point clouds / landmark lists.

python -m openfly_agent.sim.cli render --seed 0 --pose -200 -100 40 0.3 --pitch -45 --out frame.png --boxes
python -m openfly_agent.sim.cli export --seed 0 --out city.ply [--spacing 2] [--ascii] [--ground]
python -m openfly_agent.sim.cli landmarks --seed 0 --out landmarks.jsonl
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from openfly_agent.sim.city import CityConfig, generate_city, scene_id_of
from openfly_agent.sim.embedded import EmbeddedSimConfig, EmbeddedSimulator
from openfly_agent.sim.pointcloud import write_points
from openfly_agent.utils.geometry import Pose
from openfly_agent.utils.logging_utils import setup_logging

logger = logging.getLogger(__name__)


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


def _render(args: argparse.Namespace) -> None:
    import cv2

    cfg = EmbeddedSimConfig(width=args.width, height=args.height, city=CityConfig(size_m=args.size_m))
    with EmbeddedSimulator(cfg) as sim:
        obs = sim.render(scene_id_of(args.seed), Pose(*args.pose), args.pitch)
    rgb = draw_boxes(obs.rgb, obs.boxes) if args.boxes else obs.rgb
    cv2.imwrite(str(args.out), rgb[..., ::-1])
    print(f"wrote {args.out}: {len(obs.boxes)} landmark boxes")


def _export(args: argparse.Namespace) -> None:
    city = generate_city(args.seed, CityConfig(size_m=args.size_m))
    points = city.point_cloud(args.spacing, include_ground=args.ground)
    write_points(args.out, points, binary=not args.ascii)
    print(f"wrote {args.out}: {len(points)} points of {city.scene_id}")


def _landmarks(args: argparse.Namespace) -> None:
    city = generate_city(args.seed, CityConfig(size_m=args.size_m))
    with open(args.out, "w") as f:
        for lm in city.landmarks:
            record = {k: getattr(lm, k) for k in ("landmark_id", "type", "color", "size", "shape", "feature")}
            record.update(position=list(lm.position), extent=list(lm.extent), description=lm.description())
            f.write(json.dumps(record) + "\n")
    print(f"wrote {args.out}: {len(city.landmarks)} landmarks of {city.scene_id}")


PROG = "python -m openfly_agent.sim.cli"
COMMANDS = {
    "render": (
        "render one frame of a city (PNG), optionally with its landmark boxes",
        f"{PROG} render --seed 0 --pose -200 -100 40 0.3 --pitch -45 --out frame.png --boxes",
    ),
    "export": (
        "export a city's surface as a point cloud (.ply / .pcd)",
        f"{PROG} export --seed 0 --out city.ply --spacing 2",
    ),
    "landmarks": (
        "write a city's landmark list (JSON lines)",
        f"{PROG} landmarks --seed 0 --out landmarks.jsonl",
    ),
}


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults in every option's help, examples kept as written."""


def build_parser() -> argparse.ArgumentParser:
    """One sub-command per output; every option shows its default, every help ends with an example."""
    examples = "examples:\n" + "\n".join(f"  {example}" for _, example in COMMANDS.values())
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__.split("\n\n")[0], epilog=examples, formatter_class=_HelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name, (text, example) in COMMANDS.items():
        p = sub.add_parser(
            name, help=text, description=text, epilog=f"example:\n  {example}", formatter_class=_HelpFormatter
        )
        p.add_argument("--seed", type=int, default=0, help="city seed (scene id embedded-<seed>)")
        p.add_argument("--size-m", type=float, default=1000.0, help="city side in metres")
        p.add_argument("--out", type=Path, required=True, help="file to write")
        if name == "render":
            p.add_argument(
                "--pose", type=float, nargs=4, default=[0.0, 0.0, 60.0, 0.0], metavar=("X", "Y", "Z", "YAW"),
                help="camera position in metres and yaw in radians (counter-clockwise from +x)",
            )  # fmt: skip
            p.add_argument("--pitch", type=float, default=0.0, help="degrees, negative = down")
            p.add_argument("--width", type=int, default=224, help="frame width in pixels")
            p.add_argument("--height", type=int, default=224, help="frame height in pixels")
            p.add_argument("--boxes", action="store_true", help="draw the landmark boxes")
        elif name == "export":
            p.add_argument("--spacing", type=float, default=2.0, help="metres between surface samples")
            p.add_argument("--ascii", action="store_true", help="ASCII instead of binary")
            p.add_argument("--ground", action="store_true", help="also sample the ground plane")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    setup_logging()
    {"render": _render, "export": _export, "landmarks": _landmarks}[args.command](args)


if __name__ == "__main__":
    main()

"""The grounding dataset: rendered frames with one referring expression and box per visible landmark.

Layout of a grounding root (data_cards/grounding.md):
    frames/<scene>/part-<k>.parquet   one row per frame: image, pose, and the frame's expressions and boxes
    meta/parts/<scene>.json           written when a scene is complete (generation resumes scene by scene)
    meta/info.json                    counts per split and scene, written by `finalize_grounding`
The parquet schema declares `image` as a `datasets` `Image` feature, so `datasets.load_dataset("parquet",
data_files="frames/**/*.parquet")` reads it as is. Training draws (frame, expression) samples from it.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from openfly_agent import constants as C
from openfly_agent.data.frames import decode_image
from openfly_agent.data.parquet_io import write_table_atomic
from openfly_agent.data.records import check_box
from openfly_agent.data.schema import SchemaError
from openfly_agent.utils.files import write_text_atomic

logger = logging.getLogger(__name__)

FRAMES_DIR = "frames"
PARTS_DIR = "meta/parts"
INFO_JSON = "meta/info.json"
SCHEMA_VERSION = 1

GROUNDING_SCHEMA = pa.schema(
    [
        pa.field("image", pa.struct([pa.field("bytes", pa.binary()), pa.field("path", pa.string())])),
        pa.field("frame_id", pa.string()),
        pa.field("scene_id", pa.string()),
        pa.field("split", pa.string()),
        pa.field("source_episode", pa.string()),  # the trajectory whose pose was rendered
        pa.field("pose", pa.list_(pa.float64(), 4)),  # x, y, z (m), yaw (rad)
        pa.field("pitch_deg", pa.float64()),
        pa.field("landmark_ids", pa.list_(pa.string())),
        pa.field("expressions", pa.list_(pa.string())),
        pa.field("boxes", pa.list_(pa.list_(pa.float64(), 4))),  # (cx, cy, w, h) per expression
        pa.field("relations", pa.list_(pa.string())),  # "" when no relation word was needed
    ],
    metadata={
        "huggingface": json.dumps(
            {
                "info": {
                    "features": {
                        "image": {"_type": "Image"},
                        "frame_id": {"dtype": "string", "_type": "Value"},
                        "scene_id": {"dtype": "string", "_type": "Value"},
                        "split": {"dtype": "string", "_type": "Value"},
                        "source_episode": {"dtype": "string", "_type": "Value"},
                        "pose": {
                            "feature": {"dtype": "float64", "_type": "Value"},
                            "length": 4,
                            "_type": "List",
                        },
                        "pitch_deg": {"dtype": "float64", "_type": "Value"},
                        "landmark_ids": {"feature": {"dtype": "string", "_type": "Value"}, "_type": "List"},
                        "expressions": {"feature": {"dtype": "string", "_type": "Value"}, "_type": "List"},
                        "boxes": {
                            "feature": {
                                "feature": {"dtype": "float64", "_type": "Value"},
                                "length": 4,
                                "_type": "List",
                            },
                            "_type": "List",
                        },
                        "relations": {"feature": {"dtype": "string", "_type": "Value"}, "_type": "List"},
                    }
                }
            }
        )
    },
)


@dataclass
class GroundingFrame:
    """One row of the grounding dataset (the image stays encoded until asked for)."""

    frame_id: str
    scene_id: str
    split: str
    source_episode: str
    pose: tuple[float, float, float, float]
    pitch_deg: float
    landmark_ids: list[str]
    expressions: list[str]
    boxes: np.ndarray  # (E, 4) float32 cxcywh
    relations: list[str]
    image_bytes: bytes
    file: str = ""
    row: int = 0

    def rgb(self) -> np.ndarray:
        """(H, W, 3) uint8 RGB (SchemaError naming the file and row when it does not decode)."""
        return decode_image(self.image_bytes, self.file, self.row)


def part_path(root: str | Path, scene_id: str, index: int) -> Path:
    """`frames/<scene>/part-<index>.parquet` under `root`."""
    return Path(root) / FRAMES_DIR / scene_id / f"part-{index:04d}.parquet"


def grounding_table(rows: list[dict]) -> pa.Table:
    """Rows (keys of GROUNDING_SCHEMA, `image` as {bytes, path}) -> a table; boxes are checked."""
    for row in rows:
        if not (
            len(row["landmark_ids"]) == len(row["expressions"]) == len(row["boxes"]) == len(row["relations"])
        ):
            raise ValueError(
                f"frame {row['frame_id']}: landmark_ids, expressions, boxes and relations differ in length"
            )
        for k, box in enumerate(row["boxes"]):
            check_box(box, row["frame_id"], k, "boxes")
    return pa.Table.from_pylist(rows, schema=GROUNDING_SCHEMA)


def write_scene(root: str | Path, scene_id: str, rows: list[dict], frames_per_part: int) -> list[Path]:
    """Write one scene's rows as parts (atomically), then mark the scene complete."""
    paths = []
    for index, first in enumerate(range(0, len(rows), frames_per_part)):
        path = part_path(root, scene_id, index)
        write_table_atomic(grounding_table(rows[first : first + frames_per_part]), path)
        paths.append(path)
    marker = Path(root) / PARTS_DIR / f"{scene_id}.json"
    counts = {"frames": len(rows), "expressions": int(sum(len(r["expressions"]) for r in rows))}
    write_text_atomic(
        marker, json.dumps({"scene_id": scene_id, "parts": [p.name for p in paths], **counts}) + "\n"
    )
    return paths


def scene_done(root: str | Path, scene_id: str) -> bool:
    """Whether a scene's parts are all written (its marker exists)."""
    return (Path(root) / PARTS_DIR / f"{scene_id}.json").is_file()


def finalize_grounding(root: str | Path, extra: dict | None = None) -> dict:
    """Count frames and expressions per split and scene into meta/info.json; returns the info."""
    root = Path(root)
    splits: dict[str, dict] = {}
    for path in sorted((root / FRAMES_DIR).glob("*/*.parquet")):
        table = pq.read_table(path, columns=["scene_id", "split", "expressions"])
        for scene, split, expressions in zip(*(table.column(c).to_pylist() for c in table.column_names)):
            entry = splits.setdefault(split, {"frames": 0, "expressions": 0, "scenes": set()})
            entry["frames"] += 1
            entry["expressions"] += len(expressions)
            entry["scenes"].add(scene)
    info = {
        "schema_version": SCHEMA_VERSION,
        "kind": "grounding",
        "splits": {s: {**v, "scenes": sorted(v["scenes"])} for s, v in sorted(splits.items())},
        "layout": {
            "frames": f"{FRAMES_DIR}/<scene>/part-<k>.parquet",
            "complete_scenes": f"{PARTS_DIR}/<scene>.json",
        },
        **(extra or {}),
    }
    (root / INFO_JSON).parent.mkdir(parents=True, exist_ok=True)
    (root / INFO_JSON).write_text(json.dumps(info, indent=2) + "\n")
    return info


def read_grounding_expressions(root: str | Path, splits: tuple[str, ...] = (C.SPLIT_TRAIN,)) -> set[str]:
    """The distinct expressions of `splits` under `root` (the `expressions` column only: no images read)."""
    texts: set[str] = set()
    for path in sorted((Path(root) / FRAMES_DIR).glob("*/*.parquet")):
        table = pq.read_table(path, columns=["split", "expressions"])
        for split, expressions in zip(
            table.column("split").to_pylist(), table.column("expressions").to_pylist()
        ):
            if split in splits:
                texts.update(expressions)
    return texts


def read_grounding_frames(
    root: str | Path, splits: tuple[str, ...] = (C.SPLIT_TRAIN,)
) -> list[GroundingFrame]:
    """Every frame of `splits` under `root` (encoded images kept in memory), in file order.

    Raises:
        FileNotFoundError: `root` holds no grounding parts.
        SchemaError: a row breaks the schema (file, row and column named).
    """
    paths = sorted((Path(root) / FRAMES_DIR).glob("*/*.parquet"))
    if not paths:
        raise FileNotFoundError(
            f"{root} has no grounding frames ({FRAMES_DIR}/<scene>/part-*.parquet); generate them with "
            "python -m openfly_agent.toolchain grounding"
        )
    frames = []
    for path in paths:
        try:
            table = pq.read_table(path)
        except (pa.ArrowInvalid, OSError) as err:
            raise SchemaError(str(path), "<file>", "<parquet>", f"unreadable: {err}") from err
        for r, row in enumerate(table.to_pylist()):
            if row["split"] not in splits:
                continue
            boxes = row.get("boxes") or []
            if not (len(boxes) == len(row["expressions"]) == len(row["landmark_ids"])):
                raise SchemaError(
                    str(path), r, "boxes", "expressions, landmark_ids and boxes differ in length"
                )
            frames.append(
                GroundingFrame(
                    frame_id=row["frame_id"],
                    scene_id=row["scene_id"],
                    split=row["split"],
                    source_episode=row["source_episode"],
                    pose=tuple(row["pose"]),
                    pitch_deg=float(row["pitch_deg"]),
                    landmark_ids=list(row["landmark_ids"]),
                    expressions=list(row["expressions"]),
                    boxes=np.array(
                        [check_box(b, str(path), r, "boxes") for b in boxes], dtype=np.float32
                    ).reshape(-1, 4),
                    relations=list(row["relations"]),
                    image_bytes=(row["image"] or {}).get("bytes") or b"",
                    file=str(path),
                    row=r,
                )
            )
    logger.info("%d grounding frames of %s from %s", len(frames), list(splits), root)
    return frames

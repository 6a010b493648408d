"""Resolve an episode's frames to RGB arrays: parquet `image` bytes (released or ours) or image folders.

Frames are decoded lazily and cached per process (bounded LRU of encoded episodes and of decoded
frames); no file handle is kept open, so a `FrameStore` can be used from forked DataLoader workers.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from openfly_agent import constants as C
from openfly_agent.data.parquet_io import FRAME_KEY_COLUMNS, exact_frame_key, row_frame_keys
from openfly_agent.data.schema import Episode, SchemaError

logger = logging.getLogger(__name__)

IMAGE_FOLDERS = ("images", "image")  # <root>/<folder>/<episode_id>/<frame_id>.<ext>
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def decode_image(data: bytes, file: str, record: int | str, field_name: str = "image") -> np.ndarray:
    """PNG / JPEG bytes -> (H, W, 3) uint8 RGB; SchemaError naming file, record and field if corrupt."""
    if not data:
        raise SchemaError(file, record, field_name, "no image bytes")
    bgr = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise SchemaError(file, record, field_name, f"cannot decode the image ({len(data)} bytes)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)  # (H, W, 3)


def encode_image(rgb: np.ndarray, ext: str = "png") -> bytes:
    """(H, W, 3) uint8 RGB -> PNG (lossless) or JPEG (quality 95) bytes."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB frame, got {rgb.dtype} {rgb.shape}")
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if ext in ("jpg", "jpeg") else []
    ok, buf = cv2.imencode(f".{ext}", np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise ValueError(f"OpenCV could not encode a {rgb.shape} frame as {ext}")
    return buf.tobytes()


class _LRU(OrderedDict):
    """A tiny bounded least-recently-used mapping."""

    def __init__(self, capacity: int):
        super().__init__()
        self.capacity = capacity

    def get_or_none(self, key):
        if key not in self:
            return None
        self.move_to_end(key)
        return self[key]

    def put(self, key, value) -> None:
        self[key] = value
        self.move_to_end(key)
        while len(self) > self.capacity:
            self.popitem(last=False)


class FrameStore:
    """Frames of episodes under a dataset root.

    Lookup order for an episode: `<root>/traj/<episode_id>.parquet` (the release layout, also ours);
    else a parquet in `<root>/traj/<episode_id's folder>/` whose `env_id`/`traj_id` columns name the
    episode (released file names need not equal `image_path`); else image files
    `<root>/{images,image}/<episode_id>/<frame_id>.{png,jpg,jpeg}`. Parquet rows are matched to
    `frame_ids` by `<image_id>_<frame_index>` first, else the image path stem or `image_id`
    (`match_frame_rows`), so files holding every raw frame work too; a trajectory whose rows share a frame's
    key is logged once.

    Args:
        root: the dataset root.
        cache_episodes: episodes whose encoded frames are kept (LRU).
        cache_frames: decoded frames kept (LRU).
    """

    def __init__(self, root: str | Path, cache_episodes: int = 8, cache_frames: int = 256):
        self.root = Path(root)
        self.cache_episodes, self.cache_frames = cache_episodes, cache_frames
        self._reported: set[str] = set()  # episodes whose frame-key collisions were logged
        self._reset_caches()

    def _reset_caches(self) -> None:
        self._encoded = _LRU(self.cache_episodes)  # episode_id -> (source file, [bytes | None], [row | None])
        self._decoded = _LRU(self.cache_frames)  # (episode_id, t) -> (H, W, 3) uint8
        self._dir_index: dict[Path, dict[str, Path]] = {}

    def __getstate__(self) -> dict:
        # Workers start with empty caches rather than a pickled copy of the parent's.
        state = self.__dict__.copy()
        for key in ("_encoded", "_decoded", "_dir_index"):
            state.pop(key)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._reset_caches()

    def frame(self, episode: Episode, t: int) -> np.ndarray:
        """Frame `t` of `episode` as (H, W, 3) uint8 RGB (cached)."""
        if not 0 <= t < len(episode):
            raise IndexError(f"{episode.episode_id}: frame {t} out of range 0..{len(episode) - 1}")
        key = (episode.episode_id, t)
        rgb = self._decoded.get_or_none(key)
        if rgb is None:
            source, blobs, rows = self._encoded_frames(episode)
            rgb = decode_image(
                blobs[t], str(source), rows[t] if rows[t] is not None else episode.frame_ids[t]
            )
            self._decoded.put(key, rgb)
        return rgb

    def frames(self, episode: Episode) -> list[np.ndarray]:
        """All frames of `episode`, in order."""
        return [self.frame(episode, t) for t in range(len(episode))]

    def _encoded_frames(self, episode: Episode) -> tuple[Path, list[bytes], list[int | None]]:
        cached = self._encoded.get_or_none(episode.episode_id)
        if cached is None:
            parquet = self.parquet_path(episode.episode_id)
            if parquet is not None:
                cached = (parquet, *self._read_parquet_frames(parquet, episode))
            else:
                cached = self._read_image_folder(episode)
            self._encoded.put(episode.episode_id, cached)
        return cached

    def parquet_path(self, episode_id: str) -> Path | None:
        """The trajectory parquet of `episode_id`, or None when the root has none."""
        direct = self.root / C.DATASET_TRAJ_DIR / f"{episode_id}.parquet"
        if direct.is_file():
            return direct
        folder = direct.parent
        if folder not in self._dir_index:
            self._dir_index[folder] = _index_parquet_folder(folder)
        return self._dir_index[folder].get(episode_id)

    def _read_parquet_frames(self, path: Path, episode: Episode) -> tuple[list[bytes], list[int]]:
        rows = read_parquet_rows(path, episode.episode_id)
        row_ids, shared = match_frame_rows(rows, episode.frame_ids, path)
        if shared and episode.episode_id not in self._reported:  # once per trajectory, not per cache miss
            self._reported.add(episode.episode_id)
            frame_id, named, taken = shared[0]
            logger.warning(
                "%s: %d of %d kept frames are named by more than one row (rows sharing an image path); each took "
                "the row whose <image_id>_<frame_index> is its id first, e.g. %r: rows %s, took row %d",
                path, len(shared), len(row_ids), frame_id, named, taken,
            )  # fmt: skip
        blobs = [(rows[r].get("image") or {}).get("bytes") for r in row_ids]
        return blobs, row_ids

    def _read_image_folder(self, episode: Episode) -> tuple[Path, list[bytes], list[None]]:
        for folder_name in IMAGE_FOLDERS:
            folder = self.root / folder_name / episode.episode_id
            if folder.is_dir():
                return folder, [_read_image_file(folder, f) for f in episode.frame_ids], [None] * len(episode)
        raise FileNotFoundError(
            f"no frames for episode {episode.episode_id!r} under {self.root}: expected "
            f"{C.DATASET_TRAJ_DIR}/{episode.episode_id}.parquet or images/{episode.episode_id}/<frame>.png"
        )


def match_frame_rows(
    rows: list[dict], frame_ids: list[str], path: Path
) -> tuple[list[int], list[tuple[str, list[int], int]]]:
    """The parquet row of each of `frame_ids`: the row whose `<image_id>_<frame_index>` is the id, else the first
    row whose image path stem (or `image_id`) is.

    Rows of one trajectory may share an image path (the raw rows of a merged forward move in the release): the
    path then names several rows, up to 6 m apart, and only the exact key names the frame's own.

    Returns:
        The row of each frame, and `(frame id, the rows its id names, the row taken)` for every frame whose id
        more than one row names.

    Raises:
        SchemaError: a frame that no row holds.
    """
    exact: dict[str, int] = {}
    loose: dict[str, int] = {}
    named_by: dict[str, list[int]] = {}  # every key -> the rows it names
    for r, row in enumerate(rows):
        key = exact_frame_key(row)
        if key is not None:
            exact.setdefault(key, r)
        for name in dict.fromkeys(row_frame_keys(row)):
            named_by.setdefault(name, []).append(r)
            loose.setdefault(name, r)
    row_ids, shared = [], []
    for t, frame_id in enumerate(frame_ids):
        r = exact.get(frame_id, loose.get(frame_id))
        if r is None:
            raise SchemaError(str(path), frame_id, "image", f"no row holds frame {t} ({frame_id!r})")
        row_ids.append(r)
        if len(named_by[frame_id]) > 1:
            shared.append((frame_id, named_by[frame_id], r))
    return row_ids, shared


def read_parquet_rows(path: Path, record: str) -> list[dict]:
    """The frame rows of a trajectory parquet; a truncated or corrupt file is a SchemaError naming it."""
    try:
        table = pq.read_table(path, columns=[c for c in FRAME_KEY_COLUMNS if c in pq.read_schema(path).names])
        return table.to_pylist()
    except (pa.ArrowException, OSError) as err:
        problem = " ".join(str(err).split()) or type(err).__name__
        raise SchemaError(
            str(path),
            record,
            "<parquet>",
            f"not a readable parquet file ({problem}); regenerate or re-download it",
        ) from err


def _read_image_file(folder: Path, frame_id: str) -> bytes:
    for ext in IMAGE_EXTENSIONS:
        path = folder / f"{frame_id}{ext}"
        if path.is_file():
            return path.read_bytes()
    raise SchemaError(str(folder), frame_id, "image", f"no {frame_id}{{{','.join(IMAGE_EXTENSIONS)}}} file")


def _index_parquet_folder(folder: Path) -> dict[str, Path]:
    """episode id (`env_id/traj_id` of the first row) -> parquet file, for every parquet in `folder`."""
    index: dict[str, Path] = {}
    if not folder.is_dir():
        return index
    files = sorted(folder.glob("*.parquet"))
    logger.info("indexing %d trajectory files in %s by env_id/traj_id", len(files), folder)
    for path in files:
        try:
            names = pq.read_schema(path).names
            if "env_id" not in names or "traj_id" not in names:
                continue
            first = pq.read_table(path, columns=["env_id", "traj_id"]).slice(0, 1).to_pylist()
        except (pa.ArrowException, OSError) as err:
            raise SchemaError(
                str(path), "<file>", "<parquet>", f"not a readable parquet file ({err})"
            ) from err
        if first and first[0]["env_id"] and first[0]["traj_id"]:
            index[first[0]["env_id"].replace("\\", "/").strip("/") + "/" + first[0]["traj_id"]] = path
    return index


class FrameStores:
    """Frames of episodes from several dataset roots (the main dataset and the DAgger rounds' rollouts).

    Each episode is read from the store of the root it was loaded from; episode ids must be unique overall.

    Args:
        stores_and_episodes: (store, the episodes of its root) pairs.
    """

    def __init__(self, stores_and_episodes: list[tuple[FrameStore, list[Episode]]]):
        self._store_of: dict[str, FrameStore] = {}
        for store, episodes in stores_and_episodes:
            for episode in episodes:
                if episode.episode_id in self._store_of:
                    raise ValueError(
                        f"episode {episode.episode_id} is in two datasets ({store.root} and another)"
                    )
                self._store_of[episode.episode_id] = store

    def frame(self, episode: Episode, t: int) -> np.ndarray:
        """Frame `t` of `episode` from its own root (cached by that root's store)."""
        return self._store_of[episode.episode_id].frame(episode, t)

    def frames(self, episode: Episode) -> list[np.ndarray]:
        """All frames of `episode`, in order."""
        return self._store_of[episode.episode_id].frames(episode)

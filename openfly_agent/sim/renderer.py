"""Headless OpenGL renderer of embedded cities (moderngl + EGL: Mesa llvmpipe on a CPU, NVIDIA on a GPU).

One GL context per renderer, created lazily in the process that renders (EGL contexts are not fork-safe).
Each city is uploaded once (instanced boxes + ground map texture); per frame only the camera uniforms
and the list of boxes that survive frustum / screen-size culling change. Every frame reads back RGB and
the integer instance buffer, from which each visible landmark's box is computed.
"""

from __future__ import annotations

import logging
import math
import os
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from openfly_agent.sim import shaders
from openfly_agent.sim.camera import CameraModel, frustum_planes, linear_depth, projection_matrix, view_matrix
from openfly_agent.sim.ground import rasterize_ground
from openfly_agent.sim.instance_boxes import InstanceIdError, instance_boxes
from openfly_agent.utils.geometry import Pose

logger = logging.getLogger(__name__)

EGL_INSTALL_HINT = "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri"
SKY_RGB = (0.62, 0.76, 0.90)
_DRAW_ATTEMPTS = 2  # a batch whose instance ids read back invalid is drawn once more
_GROUND_EXTENT_M = 4000.0  # the ground quad reaches this far beyond the city bounds
_INSTANCE_DTYPE = np.dtype(
    [("lo", "<f4", 3), ("hi", "<f4", 3), ("color", "<f4", 3), ("material", "<i4"), ("instance", "<i4")]
)
# Unit cube corners (bit 0 = x, bit 1 = y, bit 2 = z) and 12 triangles wound counter-clockwise from outside.
_CUBE_CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], dtype="f4")
_CUBE_TRIANGLES = np.array(
    [[0, 2, 3, 0, 3, 1], [4, 5, 7, 4, 7, 6], [0, 1, 5, 0, 5, 4],  # bottom, top, south
     [2, 6, 7, 2, 7, 3], [0, 4, 6, 0, 6, 2], [1, 3, 7, 1, 7, 5]],  # north, west, east
    dtype="i4",
)  # fmt: skip


def create_egl_context(device_index: int | None = None):
    """A standalone OpenGL 3.3+ context through EGL, or a RuntimeError that says what to install."""
    try:
        import moderngl
    except ImportError as err:
        raise ImportError("the embedded renderer needs moderngl: pip install 'moderngl>=5.10'") from err
    kwargs = {"backend": "egl", "require": 330}
    if device_index is not None:
        kwargs["device_index"] = int(device_index)
    try:
        return moderngl.create_standalone_context(**kwargs)
    except Exception as err:  # glcontext raises plain Exceptions
        raise RuntimeError(
            f"Could not create a headless OpenGL context through EGL ({type(err).__name__}: {err}). "
            f"Install the EGL / Mesa libraries: `{EGL_INSTALL_HINT}` (CPU rendering with Mesa llvmpipe); "
            "on a GPU machine the NVIDIA driver's EGL library (libEGL_nvidia) works too."
        ) from err


@dataclass
class RenderOutput:
    """One rendered frame."""

    rgb: np.ndarray  # (H, W, 3) uint8
    boxes: dict[str, np.ndarray]  # landmark id -> (4,) (cx, cy, w, h) in [0, 1], visible landmarks only
    pixel_counts: dict[str, int]  # landmark id -> visible pixels
    instance_ids: np.ndarray | None = None  # (H, W) int32: building index + 1, 0 = no landmark
    depth: np.ndarray | None = None  # (H, W) float32 metres along the view axis, inf for sky


class _SceneGPU:
    """GPU resources of one city: ground texture and quad, and `slots` instance buffers + box vertex arrays.

    Each view of a batch gets its own instance buffer (slot), filled with the boxes that survive its culling.
    """

    def __init__(self, ctx, programs, city, cube_vbo, cube_ibo, slots: int):
        table = city.box_table()
        inst = np.zeros(len(table["lo"]), dtype=_INSTANCE_DTYPE)
        for key in ("lo", "hi", "color", "material", "instance"):
            inst[key] = table[key]
        self.instances = inst
        centres = ((table["lo"] + table["hi"]) / 2).astype(np.float64)  # (P, 3)
        self.centres = centres
        self.centres_h = np.concatenate([centres, np.ones((len(centres), 1))], axis=1)  # (P, 4) homogeneous
        self.radii = (np.linalg.norm(table["hi"] - table["lo"], axis=1) / 2).astype(np.float64)  # (P,)
        self.landmark_ids = [b.landmark_id for b in city.buildings]
        self.ground_z = float(city.ground_z)
        box_prog, ground_prog = programs
        names = ("in_lo", "in_hi", "in_color", "in_material", "in_instance")
        self.instance_buffers, self.box_vaos = [], []
        for _ in range(slots):
            buf = ctx.buffer(reserve=max(1, inst.nbytes))
            content = [(cube_vbo, "3f", "in_corner"), (buf, "3f 3f 3f 1i 1i/i", *names)]
            self.instance_buffers.append(buf)
            self.box_vaos.append(ctx.vertex_array(box_prog, content, index_buffer=cube_ibo))
        gmap = rasterize_ground(city)
        self.texture = ctx.texture(gmap.rgba.shape[1::-1], 4, np.ascontiguousarray(gmap.rgba).tobytes())
        self.texture.build_mipmaps()
        self.texture.repeat_x = self.texture.repeat_y = False
        self.map_origin, self.map_size = gmap.origin, gmap.size_m
        cfg = city.config  # road markings need the street grid; hand-built cities have none
        self.roads = (
            (cfg.size_m / max(1, int(cfg.size_m // cfg.block_m)), -cfg.size_m / 2, cfg.road_m)
            if cfg
            else (0, 0, 0)
        )
        b, e = city.bounds, _GROUND_EXTENT_M
        x0, x1, y0, y1 = b.xmin - e, b.xmax + e, b.ymin - e, b.ymax + e
        quad = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y0], [x1, y1], [x0, y1]], "f4")  # CCW from above
        self.ground_vbo = ctx.buffer(quad.tobytes())
        self.ground_vao = ctx.vertex_array(ground_prog, [(self.ground_vbo, "2f", "in_xy")])

    def release(self) -> None:
        for obj in (*self.box_vaos, *self.instance_buffers, self.ground_vao, self.ground_vbo, self.texture):
            obj.release()


class _Targets:
    """Framebuffers for a grid of `grid` x `rows` tiles: colour (RGBA8) + instance ids (R32I) + depth."""

    def __init__(self, ctx, tile_size: tuple[int, int], grid: int, rows: int):
        self.grid = grid
        size = (tile_size[0] * grid, tile_size[1] * rows)
        self.buffers = (
            ctx.renderbuffer(size, 4),
            ctx.renderbuffer(size, 1, dtype="i4"),
            ctx.depth_renderbuffer(size),
        )
        color, ids, depth = self.buffers
        self.fbo = ctx.framebuffer([color, ids], depth)
        # moderngl clears all attachments with float bits, so colour and ids are cleared via their own FBOs
        self.fbo_color = ctx.framebuffer([color], depth)
        self.fbo_ids = ctx.framebuffer([ids])

    def release(self) -> None:
        for obj in (self.fbo, self.fbo_color, self.fbo_ids, *self.buffers):
            obj.release()


class CityRenderer:
    """Renders `City` objects from drone poses. Not thread-safe; one per process (or per worker).

    Up to `max_batch` views render into tiles of one framebuffer and are read back together
    (`render_batch`: one GL flush per batch); `render` is a batch of one on a single-tile target.
    """

    def __init__(
        self,
        width: int = 224,
        height: int = 224,
        hfov_deg: float = 90.0,
        *,
        near_m: float = 0.5,
        far_m: float = 4000.0,
        fog_m: float = 2500.0,
        min_box_pixels: int = 16,
        cull_px: float = 1.0,
        max_batch: int = 16,
        max_cached_scenes: int = 4,
        egl_device: int | None = None,
    ):
        self.camera = CameraModel(width, height, hfov_deg)
        if not 0 < near_m < far_m:
            raise ValueError(f"need 0 < near_m < far_m, got {near_m}, {far_m}")
        if max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {max_batch}")
        self.near_m, self.far_m, self.fog_m = float(near_m), float(far_m), float(fog_m)
        self.min_box_pixels, self.cull_px = int(min_box_pixels), float(cull_px)
        self.max_batch = int(max_batch)
        self.max_cached_scenes, self.egl_device = max(1, int(max_cached_scenes)), egl_device
        self._ctx = None
        self._pid = None
        self._scenes: OrderedDict[str, tuple[object, _SceneGPU]] = OrderedDict()
        self._proj = projection_matrix(self.camera, self.near_m, self.far_m, flip_y=True)

    # --- context and resources --------------------------------------------------------------------------

    def _ensure_context(self) -> None:
        if self._ctx is not None:
            if self._pid != os.getpid():
                raise RuntimeError(
                    "this renderer's EGL context was created in process "
                    f"{self._pid} and cannot be used after fork; create the simulator inside the worker "
                    "(multiprocessing 'spawn' context, or DataLoader workers that build their own simulator)"
                )
            return
        ctx = create_egl_context(self.egl_device)
        self._ctx, self._pid = ctx, os.getpid()
        self._programs = (
            ctx.program(vertex_shader=shaders.BOX_VERTEX, fragment_shader=shaders.BOX_FRAGMENT),
            ctx.program(vertex_shader=shaders.GROUND_VERTEX, fragment_shader=shaders.GROUND_FRAGMENT),
        )
        self._cube_vbo = ctx.buffer(_CUBE_CORNERS.tobytes())
        self._cube_ibo = ctx.buffer(_CUBE_TRIANGLES.tobytes())
        self._targets: dict[int, _Targets] = {}
        for prog in self._programs:
            prog["u_sky"].value = SKY_RGB
            prog["u_fog_density"].value = 1.0 / self.fog_m
        logger.info("EGL context: %s, OpenGL %s", ctx.info["GL_RENDERER"], ctx.info["GL_VERSION"])

    @property
    def gl_renderer(self) -> str:
        """The GL_RENDERER string (e.g. 'llvmpipe (LLVM 15.0.6, 256 bits)'); creates the context."""
        self._ensure_context()
        return self._ctx.info["GL_RENDERER"]

    def _targets_for(self, n: int) -> _Targets:
        """A single-tile target for one view (cheapest for llvmpipe), the full tile grid for batches."""
        grid = 1 if n == 1 else math.ceil(math.sqrt(self.max_batch))
        if grid not in self._targets:
            rows = 1 if n == 1 else math.ceil(self.max_batch / grid)
            self._targets[grid] = _Targets(self._ctx, (self.camera.width, self.camera.height), grid, rows)
        return self._targets[grid]

    def _scene(self, city) -> _SceneGPU:
        entry = self._scenes.get(city.scene_id)
        if entry is not None and entry[0] is city:
            self._scenes.move_to_end(city.scene_id)
            return entry[1]
        if entry is not None:  # a different City object under the same id: replace it
            self._scenes.pop(city.scene_id)[1].release()
        scene = _SceneGPU(self._ctx, self._programs, city, self._cube_vbo, self._cube_ibo, self.max_batch)
        self._scenes[city.scene_id] = (city, scene)
        while len(self._scenes) > self.max_cached_scenes:
            self._scenes.popitem(last=False)[1][1].release()
        return scene

    def close(self) -> None:
        """Release every GPU resource and the context (safe to call twice)."""
        if self._ctx is None:
            return
        if self._pid == os.getpid():
            for _, scene in self._scenes.values():
                scene.release()
            for targets in self._targets.values():
                targets.release()
            self._ctx.release()
        self._targets = {}
        self._scenes.clear()
        self._ctx = None

    # --- frames ------------------------------------------------------------------------------------------

    def render(self, city, pose: Pose, pitch_deg: float = 0.0, *, depth: bool = False, ids: bool = False):
        """Render `city` from `pose` with the camera pitched by `pitch_deg` (negative = down).

        Returns a `RenderOutput` with RGB, the boxes of landmarks with >= min_box_pixels visible pixels,
        and optionally the instance-id image and metric depth.
        """
        return self.render_batch(city, [pose], [pitch_deg], depth=depth, ids=ids)[0]

    def render_batch(self, city, poses, pitches_deg, *, depth: bool = False, ids: bool = False):
        """`render` for many views of one city at once: list of `RenderOutput`, in the order of `poses`."""
        if len(poses) != len(pitches_deg):
            raise ValueError(f"got {len(poses)} poses but {len(pitches_deg)} pitches")
        self._ensure_context()
        scene = self._scene(city)
        out: list[RenderOutput] = []
        for first in range(0, len(poses), self.max_batch):
            views = list(
                zip(poses[first : first + self.max_batch], pitches_deg[first : first + self.max_batch])
            )
            targets = self._targets_for(len(views))
            for attempt in range(_DRAW_ATTEMPTS):
                self._draw(scene, targets, views)
                try:
                    out += self._read_back(scene, targets, len(views), depth, ids)
                    break
                except InstanceIdError as err:  # seen once in ~10^5 llvmpipe frames: draw the batch again
                    if attempt == _DRAW_ATTEMPTS - 1:
                        raise
                    logger.warning(
                        "%s: invalid instance ids read back (%s); drawing the batch again", city.scene_id, err
                    )
        return out

    def _tile(self, grid: int, k: int) -> tuple[int, int, int, int]:
        """GL viewport (x, y, w, h) of tile k; GL row y is memory row y, so tile k starts at row y."""
        w, h = self.camera.width, self.camera.height
        return (k % grid) * w, (k // grid) * h, w, h

    def _used_region(self, grid: int, n: int) -> tuple[int, int, int, int]:
        """(x, y, w, h) covering tiles 0..n-1."""
        cols, rows = min(n, grid), math.ceil(n / grid)
        return 0, 0, cols * self.camera.width, rows * self.camera.height

    def _visible_instances(self, scene: _SceneGPU, view_proj: np.ndarray, eye: np.ndarray) -> np.ndarray:
        """Instances whose bounding sphere meets the frustum and spans >= cull_px pixels (radius)."""
        signed = scene.centres_h @ frustum_planes(view_proj).T  # (P, 6) signed distances to the planes
        inside = signed.min(axis=1) >= -scene.radii
        offset = scene.centres - eye  # (P, 3)
        distance_sq = np.einsum("ij,ij->i", offset, offset)
        large = (scene.radii * self.camera.focal_px) ** 2 >= self.cull_px**2 * distance_sq
        return scene.instances[inside & large]

    def _draw(self, scene: _SceneGPU, targets: _Targets, views: list[tuple[Pose, float]]) -> None:
        ctx = self._ctx
        ctx.scissor = self._used_region(targets.grid, len(views))  # clear only the tiles in use
        targets.fbo_color.use()
        targets.fbo_color.clear(*SKY_RGB, 1.0, depth=1.0)
        targets.fbo_ids.clear(0.0, 0.0, 0.0, 0.0)
        targets.fbo.use()
        ctx.enable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.front_face = "cw"  # the y flip of the projection mirrors the winding
        box_prog, ground_prog = self._programs
        ground_prog["u_ground_z"].value = scene.ground_z
        ground_prog["u_map_origin"].value = scene.map_origin
        ground_prog["u_map_size"].value = scene.map_size
        ground_prog["u_roads"].value = scene.roads
        ground_prog["u_ground"].value = 0
        scene.texture.use(0)
        for k, (pose, pitch_deg) in enumerate(views):
            ctx.viewport = ctx.scissor = self._tile(targets.grid, k)
            view_proj = self._proj @ view_matrix(pose, pitch_deg)  # (4, 4)
            mvp = view_proj.T.astype("f4").tobytes()  # GL wants column-major
            for prog in self._programs:
                prog["u_view_proj"].write(mvp)
                prog["u_cam_pos"].value = tuple(pose.position)
            visible = self._visible_instances(scene, view_proj, pose.position)
            if len(visible):  # boxes first: the ground behind them then fails the early depth test
                scene.instance_buffers[k].write(visible.tobytes())
                scene.box_vaos[k].render(instances=len(visible))
            scene.ground_vao.render()
        ctx.scissor = None

    def _read_back(self, scene: _SceneGPU, targets: _Targets, n: int, want_depth: bool, want_ids: bool):
        w, h = self.camera.width, self.camera.height
        region = self._used_region(targets.grid, n)
        fbo = targets.fbo
        rgb = np.empty((region[3], region[2], 3), dtype=np.uint8)
        fbo.read_into(rgb, viewport=region, components=3, attachment=0, alignment=1)
        id_image = np.empty((region[3], region[2]), dtype=np.int32)
        fbo.read_into(id_image, viewport=region, components=1, attachment=1, alignment=1, dtype="i4")
        depth = None
        if want_depth:
            raw = fbo.read(viewport=region, components=1, attachment=-1, dtype="f4", alignment=1)
            depth = linear_depth(
                np.frombuffer(raw, np.float32).reshape(region[3], region[2]), self.near_m, self.far_m
            )
        outputs = []
        for k in range(n):
            x, y, _, _ = self._tile(targets.grid, k)
            tile = (slice(y, y + h), slice(x, x + w))
            tile_ids = np.ascontiguousarray(id_image[tile])
            visible, boxes, counts = instance_boxes(tile_ids, len(scene.landmark_ids), self.min_box_pixels)
            names = [scene.landmark_ids[i - 1] for i in visible]
            outputs.append(
                RenderOutput(
                    rgb=np.ascontiguousarray(rgb[tile]),
                    boxes=dict(zip(names, boxes)),
                    pixel_counts=dict(zip(names, counts.tolist())),
                    instance_ids=tile_ids if want_ids else None,
                    depth=None if depth is None else np.ascontiguousarray(depth[tile]),
                )
            )
        return outputs

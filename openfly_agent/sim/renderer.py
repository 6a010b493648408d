"""Headless OpenGL renderer of embedded cities (moderngl + EGL: Mesa llvmpipe on a CPU, NVIDIA on a GPU).

One GL context per renderer, created lazily in the process that renders (EGL contexts are not fork-safe).
Each city is uploaded once (instanced boxes + ground map texture); per frame only the camera uniforms
and the list of boxes that survive frustum / screen-size culling change. Every frame reads back RGB and
the integer instance buffer, from which each visible landmark's box is computed.
"""

from __future__ import annotations

import logging
import os
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from openfly_agent.sim import shaders
from openfly_agent.sim.camera import CameraModel, frustum_planes, linear_depth, projection_matrix, view_matrix
from openfly_agent.sim.ground import rasterize_ground
from openfly_agent.sim.instance_boxes import instance_boxes
from openfly_agent.utils.geometry import Pose

logger = logging.getLogger(__name__)

EGL_INSTALL_HINT = "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri"
SKY_RGB = (0.62, 0.76, 0.90)
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
    """GPU resources of one city: ground texture, instance table and the two vertex arrays."""

    def __init__(self, ctx, programs, city, cube_vbo, cube_ibo):
        table = city.box_table()
        inst = np.zeros(len(table["lo"]), dtype=_INSTANCE_DTYPE)
        for key in ("lo", "hi", "color", "material", "instance"):
            inst[key] = table[key]
        self.instances = inst
        self.centres = ((table["lo"] + table["hi"]) / 2).astype(np.float64)  # (P, 3)
        self.radii = (np.linalg.norm(table["hi"] - table["lo"], axis=1) / 2).astype(np.float64)  # (P,)
        self.landmark_ids = [b.landmark_id for b in city.buildings]
        self.ground_z = float(city.ground_z)
        self.instance_buffer = ctx.buffer(reserve=max(1, inst.nbytes))
        box_prog, ground_prog = programs
        self.box_vao = ctx.vertex_array(
            box_prog,
            [
                (cube_vbo, "3f", "in_corner"),
                (
                    self.instance_buffer,
                    "3f 3f 3f 1i 1i/i",
                    "in_lo",
                    "in_hi",
                    "in_color",
                    "in_material",
                    "in_instance",
                ),
            ],
            index_buffer=cube_ibo,
        )
        gmap = rasterize_ground(city)
        self.texture = ctx.texture(gmap.rgba.shape[1::-1], 4, np.ascontiguousarray(gmap.rgba).tobytes())
        self.texture.build_mipmaps()
        self.texture.repeat_x = self.texture.repeat_y = False
        self.map_origin, self.map_size = gmap.origin, gmap.size_m
        cfg = city.config
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
        for obj in (self.box_vao, self.ground_vao, self.instance_buffer, self.ground_vbo, self.texture):
            obj.release()


class CityRenderer:
    """Renders `City` objects from drone poses. Not thread-safe; one per process (or per worker)."""

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
        cull_px: float = 0.5,
        max_cached_scenes: int = 4,
        egl_device: int | None = None,
    ):
        self.camera = CameraModel(width, height, hfov_deg)
        if not 0 < near_m < far_m:
            raise ValueError(f"need 0 < near_m < far_m, got {near_m}, {far_m}")
        self.near_m, self.far_m, self.fog_m = float(near_m), float(far_m), float(fog_m)
        self.min_box_pixels, self.cull_px = int(min_box_pixels), float(cull_px)
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
        size = (self.camera.width, self.camera.height)
        self._color_rb = ctx.renderbuffer(size, 4)
        self._id_rb = ctx.renderbuffer(size, 1, dtype="i4")
        self._depth_rb = ctx.depth_renderbuffer(size)
        self._fbo = ctx.framebuffer([self._color_rb, self._id_rb], self._depth_rb)
        # moderngl clears all attachments with float bits, so colour and ids are cleared via their own FBOs
        self._fbo_color = ctx.framebuffer([self._color_rb], self._depth_rb)
        self._fbo_ids = ctx.framebuffer([self._id_rb])
        for prog in self._programs:
            prog["u_sky"].value = SKY_RGB
            prog["u_fog_density"].value = 1.0 / self.fog_m
        logger.info("EGL context: %s, OpenGL %s", ctx.info["GL_RENDERER"], ctx.info["GL_VERSION"])

    @property
    def gl_renderer(self) -> str:
        """The GL_RENDERER string (e.g. 'llvmpipe (LLVM 15.0.6, 256 bits)'); creates the context."""
        self._ensure_context()
        return self._ctx.info["GL_RENDERER"]

    def _scene(self, city) -> _SceneGPU:
        entry = self._scenes.get(city.scene_id)
        if entry is not None and entry[0] is city:
            self._scenes.move_to_end(city.scene_id)
            return entry[1]
        if entry is not None:  # a different City object under the same id: replace it
            self._scenes.pop(city.scene_id)[1].release()
        scene = _SceneGPU(self._ctx, self._programs, city, self._cube_vbo, self._cube_ibo)
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
            self._ctx.release()
        self._scenes.clear()
        self._ctx = None

    # --- frames ------------------------------------------------------------------------------------------

    def _visible_instances(self, scene: _SceneGPU, view_proj: np.ndarray, eye: np.ndarray) -> np.ndarray:
        """Instances whose bounding sphere meets the frustum and spans >= cull_px pixels (radius)."""
        planes = frustum_planes(view_proj)  # (6, 4)
        signed = scene.centres @ planes[:, :3].T + planes[:, 3]  # (P, 6)
        inside = (signed >= -scene.radii[:, None]).all(axis=1)
        distance = np.linalg.norm(scene.centres - eye, axis=1)
        large = scene.radii * self.camera.focal_px >= self.cull_px * distance
        return scene.instances[inside & large]

    def render(self, city, pose: Pose, pitch_deg: float = 0.0, *, depth: bool = False, ids: bool = False):
        """Render `city` from `pose` with the camera pitched by `pitch_deg` (negative = down).

        Returns a `RenderOutput` with RGB, the boxes of landmarks with >= min_box_pixels visible pixels,
        and optionally the instance-id image and metric depth.
        """
        self._ensure_context()
        scene = self._scene(city)
        view_proj = self._proj @ view_matrix(pose, pitch_deg)  # (4, 4)
        visible = self._visible_instances(scene, view_proj, pose.position)
        if len(visible):
            scene.instance_buffer.write(visible.tobytes())
        ctx = self._ctx
        self._fbo_color.use()
        self._fbo_color.clear(*SKY_RGB, 1.0, depth=1.0)
        self._fbo_ids.clear(0.0, 0.0, 0.0, 0.0)
        self._fbo.use()
        ctx.enable(ctx.DEPTH_TEST | ctx.CULL_FACE)
        ctx.front_face = "cw"  # the y flip of the projection mirrors the winding
        mvp = view_proj.T.astype("f4").tobytes()  # GL wants column-major
        box_prog, ground_prog = self._programs
        for prog in self._programs:
            prog["u_view_proj"].write(mvp)
        box_prog["u_cam_pos"].value = tuple(pose.position)
        ground_prog["u_cam_pos"].value = tuple(pose.position)
        if len(visible):
            scene.box_vao.render(instances=len(visible))
        ground_prog["u_ground_z"].value = scene.ground_z
        ground_prog["u_map_origin"].value = scene.map_origin
        ground_prog["u_map_size"].value = scene.map_size
        ground_prog["u_roads"].value = scene.roads
        scene.texture.use(0)
        ground_prog["u_ground"].value = 0
        scene.ground_vao.render()
        return self._read_back(scene, depth, ids)

    def _read_back(self, scene: _SceneGPU, want_depth: bool, want_ids: bool) -> RenderOutput:
        w, h = self.camera.width, self.camera.height
        rgb = np.empty((h, w, 3), dtype=np.uint8)
        self._fbo.read_into(rgb, components=3, attachment=0, alignment=1)
        id_image = np.empty((h, w), dtype=np.int32)
        self._fbo.read_into(id_image, components=1, attachment=1, alignment=1, dtype="i4")
        visible, boxes, counts = instance_boxes(id_image, len(scene.landmark_ids), self.min_box_pixels)
        names = [scene.landmark_ids[k - 1] for k in visible]
        depth = None
        if want_depth:
            raw = np.frombuffer(
                self._fbo.read(components=1, attachment=-1, dtype="f4", alignment=1), dtype=np.float32
            )
            depth = linear_depth(raw.reshape(h, w), self.near_m, self.far_m)
        return RenderOutput(
            rgb=rgb,
            boxes=dict(zip(names, boxes)),
            pixel_counts=dict(zip(names, counts.tolist())),
            instance_ids=id_image if want_ids else None,
            depth=depth,
        )

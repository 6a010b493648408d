"""Level-2 data toolchain: voxel map, landmarks, A* routes, rendering, instructions, generate pipeline.

Public names are re-exported lazily (importing the package imports nothing heavy); see docs/TOOLCHAIN.md.
"""

from __future__ import annotations

from openfly_agent.utils.imports import lazy_exports

_EXPORTS = {
    "GenerateConfig": "config",
    "generate": "generate",
    "build_planning_map": "voxel_map",
    "PlanningMap": "voxel_map",
    "segment_landmarks": "landmarks",
    "RouteSampler": "routes",
    "ActionSpaceAStar": "astar",
    "PlanningFailed": "astar",
    "build_action_sequence": "actions",
    "merge_forward": "actions",
    "prepare_scene": "pipeline",
    "plan_trajectory": "pipeline",
    "embedded_scene": "scenes",
    "real_scene": "scenes",
    "render_poses": "render",
    "make_instruction_backend": "instructions",
    "template_instruction": "instructions",
    "AStarExpert": "expert",
    "write_summary": "summary",
}

__all__ = sorted(_EXPORTS)

__getattr__ = lazy_exports(__name__, _EXPORTS)

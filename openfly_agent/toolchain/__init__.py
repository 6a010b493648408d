"""Level-3 data toolchain: voxel map, landmarks, A* routes, rendering, instructions, generate pipeline.

Callers import the module they need (`openfly_agent.toolchain.generate`, `openfly_agent.toolchain.config`); see
docs/TOOLCHAIN.md.
"""

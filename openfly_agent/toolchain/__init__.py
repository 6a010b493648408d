"""Level-2 data toolchain: voxel map, landmarks, A* routes, rendering, instructions, generate pipeline."""

"""Level-2 training: loop, optimizer and schedule, checkpoints."""

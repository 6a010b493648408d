"""Level-0 helpers: geometry, logging, imports, hub I/O."""

"""Level-1 data: episode schema, OpenFly readers, parquet writer, torch dataset and collator.

The names a reader of a dataset needs are re-exported lazily (importing the package imports nothing heavy);
the code imports the modules.
"""

from __future__ import annotations

from openfly_agent.utils.imports import lazy_exports

_EXPORTS = {  # the names the data cards' snippets import
    "ReaderOptions": "config",
    "load_openfly_dataset": "openfly_reader",
    "FrameStore": "frames",
    "compute_action_statistics": "stats",
    "NavigationStepDataset": "dataset",
}

__all__ = sorted(_EXPORTS)

__getattr__ = lazy_exports(__name__, _EXPORTS)

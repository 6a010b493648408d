"""Level-1 data: episode schema, OpenFly readers, parquet writer, torch dataset and collator.

Public names are re-exported lazily (importing the package imports nothing heavy).
"""

from __future__ import annotations

from openfly_agent.utils.imports import lazy_exports

_EXPORTS = {
    "Episode": "schema",
    "SchemaError": "schema",
    "ReaderOptions": "config",
    "HistoryConfig": "config",
    "DataConfig": "config",
    "episode_from_record": "records",
    "record_from_episode": "records",
    "read_annotation_file": "openfly_reader",
    "load_openfly_dataset": "openfly_reader",
    "split_episodes": "openfly_reader",
    "ReadReport": "openfly_reader",
    "read_parquet_episode": "parquet_io",
    "FrameStore": "frames",
    "OpenFlyDatasetWriter": "writer",
    "compute_action_statistics": "stats",
    "NavigationStepDataset": "dataset",
    "make_step_dataset": "dataset",
    "NavigationCollator": "collator",
}

__all__ = sorted(_EXPORTS)

__getattr__ = lazy_exports(__name__, _EXPORTS)

"""train.py on broken data: one line on stderr naming the file (and record and field), exit code 2.

A truncated annotation file is caught before any compute; a trajectory parquet that is half written and a
frame whose bytes do not decode are met mid-training, after the preflight has read the first frame.
"""

from __future__ import annotations

import json
import shutil

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from conftest import train_args, train_main

from openfly_agent import constants as C
from openfly_agent.data.schema import SchemaError
from openfly_agent.training.preflight import PreflightError
from openfly_agent.utils.errors import one_line, root_cause


@pytest.fixture
def dataset_copy(generated_dataset, tmp_path):
    root = tmp_path / "data"
    shutil.copytree(generated_dataset, root)
    return root


def _train_parquets(root) -> list:
    records = json.loads((root / C.DATASET_ANNOTATION_DIR / "train.json").read_text())
    return [root / C.DATASET_TRAJ_DIR / f"{r['image_path']}.parquet" for r in records]


def _errors(capsys) -> list[str]:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err[-3000:]
    return [line for line in err.splitlines() if line.startswith("train.py:")]


def test_root_cause_keeps_the_file_that_a_wrapper_names():
    inner = SchemaError("/data/Annotation/train.json", "<file>", "<json>", "not valid JSON: Expecting ','")
    try:
        try:
            raise inner
        except SchemaError as err:
            raise PreflightError(f"dataset /data, split 'train': {err}") from err
    except PreflightError as outer:
        assert "/data/Annotation/train.json" in root_cause(outer)
    worker = RuntimeError(
        "Caught SchemaError in DataLoader worker process 0.\nOriginal Traceback (most recent call last):\n"
        '  File "x.py", line 1, in <module>\nopenfly_agent.data.schema.SchemaError: /d/t.parquet: record 3: bad'
    )
    assert one_line(worker) == "/d/t.parquet: record 3: bad"


def test_truncated_annotation_names_the_file(dataset_copy, tmp_path, capsys):
    annotation = dataset_copy / C.DATASET_ANNOTATION_DIR / "train.json"
    annotation.write_bytes(annotation.read_bytes()[:3000])
    assert train_main(train_args(dataset_copy, tmp_path / "run", steps=1)) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and str(annotation) in errors[0] and "not valid JSON" in errors[0], errors


def test_half_written_parquet_mid_training_names_the_file(dataset_copy, tmp_path, capsys):
    broken = _train_parquets(dataset_copy)[1:]  # the preflight reads the first episode's first frame
    for path in broken:
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert train_main(train_args(dataset_copy, tmp_path / "run", steps=2)) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and "not a readable parquet file" in errors[0], errors
    assert any(str(path) in errors[0] for path in broken), errors


def test_frame_that_does_not_decode_mid_training_names_file_record_and_field(dataset_copy, tmp_path, capsys):
    broken = _train_parquets(dataset_copy)[1:]
    for path in broken:
        table = pq.read_table(path)
        rows = table.to_pylist()
        for row in rows:
            row["image"] = {**row["image"], "bytes": b"\x89PNG not really"}
        pq.write_table(pa.Table.from_pylist(rows, schema=table.schema), path)
    assert train_main(train_args(dataset_copy, tmp_path / "run", steps=2)) == 2
    errors = _errors(capsys)
    assert len(errors) == 1 and "field 'image': cannot decode the image" in errors[0], errors
    assert any(f"{path}: record " in errors[0] for path in broken), errors

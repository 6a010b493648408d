"""Reading the released OpenFly annotation format: the real eval_test.json and hand-broken records."""

from __future__ import annotations

import copy
import json
import logging
from collections import Counter

import numpy as np
import pytest

from openfly_agent.data.config import ReaderOptions
from openfly_agent.data.openfly_reader import (
    ReadReport,
    load_openfly_dataset,
    read_annotation_file,
    split_episodes,
)
from openfly_agent.data.schema import SchemaError
from openfly_agent.data.stats import action_histogram

# docs/OFFICIAL_OPENFLY.md 1.2, counted on the 240 records of tests/fixtures/openfly/eval_test.json
EVAL_TEST_HISTOGRAM = {9: 1992, 2: 230, 8: 218, 3: 204, 1: 195, 0: 240, 4: 62, 5: 57, -1: 366, -2: 368}
FOUR_NUMBER_POS_RECORDS = [
    17,
    26,
    101,
    135,
    177,
]  # records holding some `pos` entries with a 4th number (= yaw)


@pytest.fixture(scope="module")
def eval_test(openfly_fixtures):
    path = openfly_fixtures / "eval_test.json"
    return path, json.loads(path.read_text())


def test_eval_test_keep_reads_all_240_as_released(eval_test):
    path, raw = eval_test
    episodes = read_annotation_file(path, ReaderOptions(takeoff_landing="keep"))
    assert len(episodes) == 240
    scenes = ["env_airsim_16", "env_airsim_18", "env_airsim_23", "env_airsim_26"]
    scenes += ["env_airsim_sh", "env_airsim_gz", "env_ue_smallcity", "env_ue_bigcity"]
    assert Counter(e.scene_id for e in episodes) == dict.fromkeys(scenes, 30)
    assert action_histogram(episodes) == EVAL_TEST_HISTOGRAM
    assert sum(len(e) for e in episodes) == 3932
    assert all(e.split is None for e in episodes)  # eval_test.json names no split
    for e, r in zip(episodes, raw):
        assert e.episode_id == r["image_path"] and e.instruction == r["gpt_instruction"]
        assert e.frame_ids == r["index_list"]
        np.testing.assert_array_equal(e.goal, np.asarray(r["pos"][-1][:3]))
        assert e.pitch_deg == (-45.0 if e.category.startswith("high") else 0.0)


def test_eval_test_fourth_pos_number_is_dropped(eval_test):
    path, raw = eval_test
    with_four = [i for i, r in enumerate(raw) if any(len(p) == 4 for p in r["pos"])]
    assert with_four == FOUR_NUMBER_POS_RECORDS
    episodes = read_annotation_file(path, ReaderOptions(takeoff_landing="keep"))
    for i in with_four:
        assert episodes[i].positions.shape == (len(raw[i]["pos"]), 3)
        np.testing.assert_array_equal(episodes[i].positions, [p[:3] for p in raw[i]["pos"]])
        np.testing.assert_array_equal(episodes[i].yaws, raw[i]["yaw"])


def test_eval_test_map_relabels_phases_consistently_with_poses(eval_test):
    episodes = read_annotation_file(eval_test[0], ReaderOptions(takeoff_landing="map"))
    assert action_histogram(episodes) == {
        0: 240,
        1: 195,
        2: 230,
        3: 204,
        4: 62 + 366,
        5: 57 + 368,
        8: 218,
        9: 1992,
    }
    assert all(e.actions[-1] == 0 for e in episodes)
    climbs = Counter()
    for e in episodes:  # every ascend / descend label now moves 3 m up / down to the next frame
        for t in np.flatnonzero(np.isin(e.actions[:-1], (4, 5))):
            climbs[(int(e.actions[t]), round(e.positions[t + 1, 2] - e.positions[t, 2], 6))] += 1
    assert climbs == {(4, 3.0): 428, (5, -3.0): 425}


def test_eval_test_trim_drops_phases_and_ends_at_stop(eval_test):
    path, raw = eval_test
    episodes = read_annotation_file(path, ReaderOptions(takeoff_landing="trim"))
    assert action_histogram(episodes) == {0: 240, 1: 195, 2: 230, 3: 204, 4: 62, 5: 57, 8: 218, 9: 1992}
    assert sum(len(e) for e in episodes) == 3932 - 366 - 368
    # record 151: 9 take-off climbs, then 9, 1, STOP, then 9 landing descents
    assert episodes[151].actions.tolist() == [9, 1, 0]
    assert episodes[151].frame_ids == raw[151]["index_list"][9:12]
    np.testing.assert_array_equal(episodes[151].goal, raw[151]["pos"][11])


def test_split_is_inferred_from_release_file_names(tmp_path, eval_test):
    (tmp_path / "Annotation").mkdir()
    (tmp_path / "Annotation" / "seen.json").write_text(json.dumps(eval_test[1][:5]))
    episodes = load_openfly_dataset(tmp_path, "test_seen")
    assert [e.split for e in episodes] == ["test_seen"] * 5
    with pytest.raises(FileNotFoundError, match="unseen.json"):
        load_openfly_dataset(tmp_path, "test_unseen")


def _break(record: dict, how: str) -> dict:
    record = copy.deepcopy(record)
    if how == "pos_short":
        record["pos"] = record["pos"][:-1]
    elif how == "pos_two_numbers":
        record["pos"][3] = record["pos"][3][:2]
    elif how == "pos_five_numbers":
        record["pos"][3] = record["pos"][3][:3] + [0.0, 0.0]
    elif how == "pos_fourth_not_yaw":
        record["pos"][3] = record["pos"][3][:3] + [record["yaw"][3] + 0.5]
    elif how == "unknown_action":
        record["action"][2] = 11
    elif how == "two_stops":
        record["action"][2] = 0
    elif how == "no_stop":
        record["action"][-1] = 1
    elif how == "float_action":
        record["action"][1] = 9.0
    elif how == "yaw_nan":
        record["yaw"][0] = float("nan")
    elif how == "index_list_long":
        record["index_list"] = record["index_list"] + ["x"]
    elif how == "action_long":
        record["action"] = record["action"] + [-2]
    elif how == "no_instruction":
        del record["gpt_instruction"]
    elif how == "absolute_path":
        record["image_path"] = "/" + record["image_path"]
    return record


@pytest.mark.parametrize(
    ("how", "field"),
    [
        ("pos_short", "pos"),
        ("pos_two_numbers", "pos"),
        ("pos_five_numbers", "pos"),
        ("pos_fourth_not_yaw", "pos"),
        ("unknown_action", "action"),
        ("two_stops", "action"),
        ("no_stop", "action"),
        ("float_action", "action"),
        ("yaw_nan", "yaw"),
        ("index_list_long", "index_list"),
        ("action_long", "action"),  # the other three lists agree: the action list is the one too long
        ("no_instruction", "gpt_instruction"),
        ("absolute_path", "image_path"),
    ],
)
def test_schema_errors_name_file_record_and_field(tmp_path, eval_test, how, field):
    records = copy.deepcopy(eval_test[1][:3])
    records[1] = _break(records[1], how)
    path = tmp_path / "broken.json"
    path.write_text(json.dumps(records))
    with pytest.raises(SchemaError) as info:
        read_annotation_file(path, ReaderOptions())
    err = info.value
    assert (err.file, err.record, err.field_name) == (str(path), 1, field)
    assert str(path) in str(err) and "record 1" in str(err) and f"'{field}'" in str(err)


def test_non_strict_skips_and_reports_bad_records(tmp_path, eval_test, caplog):
    records = copy.deepcopy(eval_test[1][:4])
    records[0] = _break(records[0], "two_stops")
    records[3] = _break(records[3], "pos_two_numbers")
    records.append(copy.deepcopy(records[1]))  # a duplicate episode id
    path = tmp_path / "train.json"
    path.write_text(json.dumps(records))
    report = ReadReport()
    with caplog.at_level(logging.WARNING):
        episodes = read_annotation_file(path, ReaderOptions(strict=False), report=report)
    assert [e.episode_id for e in episodes] == [records[1]["image_path"], records[2]["image_path"]]
    assert [e.split for e in episodes] == ["train", "train"]
    assert [(e.record, e.field_name) for e in report.errors] == [(0, "action"), (3, "pos"), (4, "image_path")]
    assert (report.records, report.episodes) == (5, 2)
    assert sum("skipping a bad record" in r.message for r in caplog.records) == 3


def test_the_reader_says_what_it_changed_in_one_line(eval_test, caplog):
    """eval_test.json read with `trim`: 366 take-off and 368 landing frames dropped, 92 `pos` entries that carry
    the yaw as a 4th number (docs/OFFICIAL_OPENFLY.md 1.2, data_cards/openfly_released.md section 4)."""
    path = eval_test[0]
    with caplog.at_level(logging.INFO, logger="openfly_agent.data.openfly_reader"):
        read_annotation_file(path, ReaderOptions(takeoff_landing="trim"))
        read_annotation_file(path, ReaderOptions(takeoff_landing="map", merged_forward_position="start"))
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: 240 of 240 records read; the reader changed 734 take-off/landing frames trimmed, "
        "92 four-number positions cut to three",
        f"{path}: 240 of 240 records read; the reader changed 734 take-off/landing labels mapped to "
        "ascend/descend, 92 four-number positions cut to three, 724 forward labels moved to where their motion "
        "starts, 21 forward labels left as released (not a pure move)",
    ]


def test_invalid_json_file_is_a_schema_error(tmp_path):
    path = tmp_path / "train.json"
    path.write_text('{"image_path": ')
    with pytest.raises(SchemaError, match="not valid JSON"):
        read_annotation_file(path)
    path.write_text('{"image_path": "a"}')
    with pytest.raises(SchemaError, match="list of records"):
        read_annotation_file(path)


def test_reader_options_reject_unknown_values():
    with pytest.raises(ValueError, match="takeoff_landing"):
        ReaderOptions(takeoff_landing="drop")
    with pytest.raises(ValueError, match="merged_forward_position"):
        ReaderOptions(merged_forward_position="middle")


def test_split_episodes_is_deterministic_and_disjoint(eval_test):
    episodes = read_annotation_file(eval_test[0])
    keep, held = split_episodes(episodes, 0.25, seed=3)
    keep2, held2 = split_episodes(list(reversed(episodes)), 0.25, seed=3)
    assert {e.episode_id for e in held} == {e.episode_id for e in held2}
    assert len(keep) + len(held) == 240 and not {e.episode_id for e in keep} & {e.episode_id for e in held}
    assert 30 <= len(held) <= 90

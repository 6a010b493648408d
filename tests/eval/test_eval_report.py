"""The tables of eval/report.py on hand-built records: success counts, intervals, early STOPs, breakdowns."""

from __future__ import annotations

from openfly_agent.eval.report import policy_results, results_markdown, route_class, start_distance_bin
from openfly_agent.rollout.record import EpisodeRecord

SPLIT = "test_unseen"


def _record(episode_id: str, goal_x: float, actions: list[int]) -> EpisodeRecord:
    """Start at (0, 0, 10) facing +x, goal `goal_x` m ahead; forward (1) moves 3 m, STOP (0) stays."""
    poses = [[0.0, 0.0, 10.0, 0.0]]
    for action in actions:
        poses.append([poses[-1][0] + (3.0 if action == 1 else 0.0), 0.0, 10.0, 0.0])
    stopped = actions[-1] == 0
    return EpisodeRecord(
        split=SPLIT,
        episode_id=episode_id,
        scene_id=episode_id.split("/")[0],
        policy="p",
        instruction="go",
        goal=[goal_x, 0.0, 10.0],
        reference_path=[[0.0, 0.0, 10.0], [goal_x, 0.0, 10.0]],
        actions=actions,
        poses=poses,
        stopped=stopped,
        end_reason="stop" if stopped else "max_steps",
    )


# Under `standard`: a success (NE 0), a STOP at the start (early), a STOP after 15 m of 120 (far), no STOP.
RECORDS = [
    _record("s/astar_data/low_short/a", 6.0, [1, 1, 0]),
    _record("s/astar_data/low_long/b", 60.0, [0]),
    _record("s/astar_data/high_long_updown/c", 120.0, [1] * 5 + [0]),
    _record("s/other/d", 250.0, [1] * 4),
]


def test_route_class_and_start_distance_come_from_the_id_and_the_poses():
    assert route_class("s/astar_data/medium_average_updown/t0") == ("average", "medium")
    assert route_class("s/astar_data/weird/t0") == ("unknown", "unknown")
    assert route_class("s/t0") == ("unknown", "unknown")
    assert [start_distance_bin(r) for r in RECORDS] == ["< 50 m", "50-100 m", "100-150 m", ">= 200 m"]
    assert start_distance_bin(_record("s/x", 50.0, [0])) == "50-100 m"  # a bin holds its lower edge


def test_results_table_says_k_of_n_with_intervals_and_breakdowns():
    results = policy_results("p", RECORDS, ["standard"], {"split_episodes": {SPLIT: 260}})
    table = results["splits"][SPLIT]["standard"]
    assert table["overall"]["successes"] == 1
    assert set(table["breakdowns"]) == {"route_length", "flight_height", "start_distance"}
    assert list(table["breakdowns"]["route_length"]) == [
        "short",
        "long",
        "unknown",
    ]  # table order, not sorted
    assert table["breakdowns"]["flight_height"]["low"]["successes"] == 1
    assert table["breakdowns"]["flight_height"]["low"]["episodes"] == 2
    text = results_markdown(results)
    # Wilson 1 of 4: z^2/n = 0.960365, centre = 0.730182 / 1.960365 = 0.372473, half = 1.959964
    # * sqrt(0.046875 + 0.060023) / 1.960365 = 0.326886 -> 4.6 .. 69.9 %.
    assert "| 4 | 0 | 1 of 4 |" in text and "| 25.0 (4.6-69.9) |" in text
    assert "Evaluated 4 of the split's 260 episodes" in text
    # NE bootstrap over 4 episodes (0, 60, 105, 238 m): each resample repeats one value with probability
    # 1 / 256 < 2.5 %, so the interval lies strictly inside 0 .. 238.
    low, high = table["overall"]["ne_ci95"]
    assert 0.0 < low < table["overall"]["ne_m"] < high < 238.0
    # Breakdowns: 1 of 1 short (Wilson low = 1 / (1 + z^2) = 20.7 %), 0 of 2 long (high = z^2 / (2 + z^2) = 65.8 %).
    assert "| short | 1 | 1 of 1 |" in text and "| 100.0 (20.7-100.0) |" in text
    assert "| long | 2 | 0 of 2 |" in text and "| 0.0 (0.0-65.8) |" in text
    assert "by start-goal distance" in text and "| >= 200 m | 1 | 0 of 1 |" in text
    # Where they end: success, early STOP, STOP far, step limit: one each.
    assert "| Early STOP (%) |" in text
    assert f"| {SPLIT} / `standard` | 4 | 25.0 (4.6-69.9) | 25.0 | 25.0 | 0.0 | 0.0 | 25.0 |" in text

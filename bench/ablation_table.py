"""Finished recipe runs side by side (openfly_agent/recipe/report.py): the ablation table, as markdown + JSON.

Each --run is NAME=FOLDER, a recipe run's output_dir; the row reads its navigation stage's metrics and its
evaluations (eval/ and eval-<cities>/), so every number in the table comes from those files. The first --run is
the reference arm: every other row carries its agent's SR difference from the reference's on the same episodes
(per main test split, standard profile, Newcombe 95 % interval and exact McNemar p; python -m
openfly_agent.eval.compare gives the full comparison of two runs):

    python bench/ablation_table.py --run recipe=outputs/recipe \\
        --run current_frame=outputs/ablations/current_frame --json outputs/ablations/table.json
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def name_and_folder(value: str) -> tuple[str, str]:
    """--run: NAME=FOLDER (or a bare FOLDER, named after its last part)."""
    name, sep, folder = value.partition("=")
    if not sep:
        return Path(value).name, value
    if not name or not folder:
        raise argparse.ArgumentTypeError(f"NAME=FOLDER, got {value!r}")
    return name, folder


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--run",
        type=name_and_folder,
        action="append",
        required=True,
        help="NAME=FOLDER; the first is the reference",
    )
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = parser.parse_args()

    from openfly_agent.recipe.report import markdown_table, read_runs  # lazy: after the sys.path insert above

    try:
        runs = read_runs(args.run)
    except (FileNotFoundError, ValueError) as err:
        sys.exit(f"ablation_table: {err}")
    sys.stdout.write(markdown_table(runs))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps([asdict(r) for r in runs], indent=2) + "\n")


if __name__ == "__main__":
    main()

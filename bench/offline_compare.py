"""Two navigation runs' held-out action accuracy, paired on the same samples (bench/analysis/offline_compare.py).

Runs each run's agent (its last checkpoint) over the same evenly spaced samples of a split (default: the first
run's data.test_split) and prints both accuracies, the samples only one of them predicts, and the difference
(second - first) with a 95 % interval from a bootstrap over episodes; --json writes the figures too:

    python bench/offline_compare.py --run current_frame=outputs/ablations/current_frame/navigation \\
        --run keyframes_merging=outputs/ablations/keyframes_merging/navigation --max_samples 4096

Run it from the directory the runs trained in (their configs name their datasets by relative path).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.ablation_table import name_and_folder  # noqa: E402  (after the sys.path insert)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--run", type=name_and_folder, action="append", required=True, help="NAME=FOLDER, twice: A then B"
    )
    parser.add_argument("--split", default=None, help="default: the first run's data.test_split")
    parser.add_argument("--max_samples", type=int, default=4096, help="0: every sample of the split")
    parser.add_argument("--batch_size", type=int, default=32)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = parser.parse_args()
    if len(args.run) != 2:
        parser.error(f"--run twice (A, then B), got {len(args.run)}")

    import torch  # lazy: --help stays fast

    from bench.analysis.offline_compare import collect_step_hits, paired_hits, paired_markdown

    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    (name_a, run_a), (name_b, run_b) = args.run
    try:
        a = collect_step_hits(run_a, args.split, args.max_samples or None, args.batch_size)
        b = collect_step_hits(run_b, args.split or a.split, args.max_samples or None, args.batch_size)
        figures = paired_hits(a, b)
    except (FileNotFoundError, ValueError) as err:
        sys.exit(f"offline_compare: {err}")
    figures.update(a=name_a, b=name_b, run_a=run_a, run_b=run_b)
    print(paired_markdown(figures, name_a, name_b))
    print(f"{time.perf_counter() - start:.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()

"""What an eval output folder says about the release: whose weights it evaluated, and the baselines beside it.

eval.py writes `<output_dir>/<policy>/run_identity.json` for every policy (eval/run.py): its settings and, for
the agent policies, `weights`, the `checkpoint_fingerprint` of the weights it loaded. The release computes the
same fingerprint for its checkpoint and refuses results of other weights; the other policies of the same run
(random, stop, box_servo, agent_true_box, ...) become the card's reference rows.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from openfly_agent.eval.config import AGENT_POLICIES, POLICY_NAMES
from openfly_agent.eval.run import RUN_IDENTITY_NAME, read_run_identity, same_weights
from openfly_agent.hub.results import AGENT_POLICY, EvalResults, ResultsError, parse_results
from openfly_agent.rollout.checkpoints import (
    checkpoint_fingerprint,
    describe_fingerprint,
    weight_file_changes,
)

logger = logging.getLogger(__name__)

# run_identity.json keys every policy of one eval run shares (eval/config.py `result_identity`); a baseline
# whose values differ was run on other episodes or another simulator and is left off the card.
SHARED_SETTINGS = (
    "dataset_root",
    "reader",
    "max_steps",
    "sim_type",
    "sim_width",
    "sim_height",
    "sim_occupancy",
)


def check_results_weights(results_file: Path, checkpoint: Path) -> None:
    """Refuse results that eval.py did not compute on the weights of `checkpoint`.

    Raises:
        ResultsError: no run_identity.json beside `results_file`, it records no weights, or other weights than
            the checkpoint's (one line naming both).
    """
    identity = _identity(results_file.parent)
    recorded = identity.get("weights") if identity else None
    if not recorded:
        raise ResultsError(
            f"{results_file.parent / RUN_IDENTITY_NAME} is missing or names no weights, so the weights these "
            f"results evaluated are unknown: pass the eval output folder eval.py wrote for {checkpoint}"
        )
    current = checkpoint_fingerprint(str(checkpoint))
    if same_weights(recorded, current):
        return
    if recorded.get("folder") == current.get("folder"):  # e.g. a resume that saved the same step again
        what = (
            f"{current.get('folder')} as it was then, and its weights changed since "
            f"({weight_file_changes(recorded, current)})"
        )
    else:
        what = f"{describe_fingerprint(recorded)}, the checkpoint is {describe_fingerprint(current)}"
    raise ResultsError(
        f"--results {results_file} evaluated other weights than --checkpoint: its {RUN_IDENTITY_NAME} names "
        f"{what}; evaluate the checkpoint (eval.py --checkpoint {checkpoint} --output_dir <new folder>) and pass "
        "those results"
    )


def load_baselines(results_file: Path, agent: EvalResults) -> list[EvalResults]:
    """The other policies eval.py ran beside the agent in the same output folder, in eval's policy order.

    Kept when their run settings and episode counts equal the agent's (and, for `agent_true_box`, its weights
    are the agent's); others are left out with a log line. Results in any other folder layout give none.
    """
    root = results_file.parent.parent
    if results_file.parent.name != AGENT_POLICY:
        return []
    agent_identity = _identity(results_file.parent) or {}
    baselines = []
    for name in POLICY_NAMES:
        folder = root / name
        if name == AGENT_POLICY or not (folder / results_file.name).is_file():
            continue
        reason = _mismatch(_identity(folder), agent_identity, name)
        try:
            results = parse_results(json.loads((folder / results_file.name).read_text()), str(folder), name)
        except (ResultsError, OSError, json.JSONDecodeError) as err:
            reason = reason or str(err)
            results = None
        if results is not None and not reason:
            counts = [(row.split, row.profile, row.num_episodes) for row in results.rows]
            if counts != [(row.split, row.profile, row.num_episodes) for row in agent.rows]:
                reason = "other episodes than the agent's"
        if reason:
            logger.info("baseline %s left off the card: %s", folder, reason)
            continue
        baselines.append(results)
    return baselines


def _identity(folder: Path) -> dict | None:
    try:
        return read_run_identity(folder)
    except (OSError, json.JSONDecodeError) as err:
        raise ResultsError(f"{folder / RUN_IDENTITY_NAME}: cannot read it ({err})") from err


def _mismatch(identity: dict | None, agent_identity: dict, name: str) -> str | None:
    """Why the baseline of `identity` does not compare with the agent's run (None when it does)."""
    if identity is None:
        return f"no {RUN_IDENTITY_NAME}"
    changed = [key for key in SHARED_SETTINGS if identity.get(key) != agent_identity.get(key)]
    if changed:
        return f"other settings ({', '.join(changed)})"
    if name in AGENT_POLICIES and not same_weights(
        identity.get("weights") or {}, agent_identity.get("weights") or {}
    ):
        return "other weights than the agent's"
    return None

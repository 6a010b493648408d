"""`python -m openfly_agent.hub {release, release-dataset, fake-hub}`: build release folders and push them.

Each command parses its config dataclass (hub/config.py) with draccus' dotted options, as train.py and eval.py
do (`--repo_id=me/x --push=true --card.tags=[a,b]`); `<command> --help` lists them. Exit codes: 0 done, 2 bad
input (one line on stderr naming the option, the file or the folder).
"""

from __future__ import annotations

import signal
import sys
import time

from openfly_agent.hub.config import DatasetReleaseConfig, FakeHubConfig, ModelReleaseConfig
from openfly_agent.hub.dataset_release import build_dataset_release
from openfly_agent.hub.fake_hub import FakeHub
from openfly_agent.hub.model_release import build_model_release
from openfly_agent.hub.push import check_push_ready, push_folder
from openfly_agent.utils.cli_help import choose_command, command_help, commands_usage, wants_help
from openfly_agent.utils.config import parse_config
from openfly_agent.utils.errors import root_cause
from openfly_agent.utils.logging_utils import setup_logging

PROG = "python -m openfly_agent.hub"
EXIT_BAD_INPUT = 2
COMMANDS = {  # name: (config class, what it does)
    "release": (
        ModelReleaseConfig,
        "Build the release folder of a checkpoint (weights, card, remote code); --push=true uploads it.",
    ),
    "release-dataset": (
        DatasetReleaseConfig,
        "Build the release folder of a generated dataset (parquet, annotations, card); --push=true uploads it.",
    ),
    "fake-hub": (
        FakeHubConfig,
        "Serve the Hub upload and download endpoints on 127.0.0.1 until Ctrl-C (docs/RELEASE.md).",
    ),
}
EXAMPLES = {
    "release": (
        f"{PROG} release --checkpoint=outputs/train/tiny --repo_id=my-user/openfly-agent-tiny "
        "--results=outputs/eval                    # writes outputs/releases/openfly-agent-tiny",
        f"HF_HUB_OFFLINE=0 {PROG} release --checkpoint=outputs/train/tiny --repo_id=my-user/openfly-agent-tiny "
        "--results=outputs/eval --overwrite=true --push=true",
    ),
    "release-dataset": (
        f"{PROG} release-dataset --dataset_root=outputs/datasets/embedded-small "
        "--repo_id=my-user/openfly-embedded --card=data_cards/embedded.md",
    ),
    "fake-hub": (
        f'{PROG} fake-hub --token="$HF_TOKEN"      # then HF_ENDPOINT=<printed url> ... --push=true',
    ),
}


def usage() -> str:
    """The help of `python -m openfly_agent.hub --help` (each command's own: `<command> --help`)."""
    summary = "Release checkpoints and datasets to the Hugging Face Hub (docs/RELEASE.md)."
    commands = {name: text for name, (_, text) in COMMANDS.items()}
    examples = [example for command_examples in EXAMPLES.values() for example in command_examples]
    return commands_usage(PROG, summary, commands, examples, name_width=16)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    chosen = choose_command(list(sys.argv[1:] if argv is None else argv), list(COMMANDS), PROG, usage())
    if isinstance(chosen, int):
        return chosen
    command, args = chosen
    config_class, description = COMMANDS[command]
    if wants_help(args):
        print(command_help(config_class, args, f"{PROG} {command}", description, EXAMPLES[command]), end="")
        return 0
    try:  # a bad option or value, a missing file, a Hub HTTP error (OSError), a folder that is not a checkpoint
        cfg = parse_config(config_class, args)
        setup_logging()
        if command == "release":
            return _release_model(cfg)
        if command == "release-dataset":
            return _release_dataset(cfg)
        return _serve_fake_hub(cfg.token)
    except Exception as err:
        from draccus.utils import DraccusException

        if not isinstance(err, (ValueError, OSError, RuntimeError, DraccusException)):
            raise
        print(f"{PROG} {command}: {root_cause(err)}", file=sys.stderr)
        return EXIT_BAD_INPUT


def _release_model(cfg: ModelReleaseConfig) -> int:
    if cfg.push:  # offline, no token or no Hub: fail before anything is written
        check_push_ready(cfg.repo_id)
    folder = build_model_release(cfg)
    print(f"release folder: {folder}")
    if cfg.push:
        url = push_folder(
            folder, cfg.repo_id, private=cfg.private, revision=cfg.revision, commit_message=cfg.commit_message
        )
        print(f"pushed: {url}")
    return 0


def _release_dataset(cfg: DatasetReleaseConfig) -> int:
    if cfg.push:
        check_push_ready(cfg.repo_id)
    folder = build_dataset_release(cfg)
    print(f"release folder: {folder}")
    if cfg.push:
        url = push_folder(
            folder,
            cfg.repo_id,
            repo_type="dataset",
            private=cfg.private,
            revision=cfg.revision,
            commit_message=cfg.commit_message,
        )
        print(f"pushed: {url}")
    return 0


def _serve_fake_hub(token: str) -> int:
    """Serve until SIGINT (Ctrl-C) or SIGTERM, then print what each repository received.

    The handlers are installed explicitly: a shell starts background jobs with SIGINT ignored, and a Python
    started that way would never see Ctrl-C / `kill -INT` and serve forever.
    """
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.default_int_handler)  # raises KeyboardInterrupt
    with FakeHub(token=token) as hub:
        try:  # the announcement inside: a signal sent as soon as it is read lands in this block
            print(f"fake Hub listening: export HF_ENDPOINT={hub.url}  (Ctrl-C to stop)", flush=True)
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
        for (repo_type, repo_id), repo in hub.repos.items():
            for branch, files in repo.branches.items():
                size = sum(map(len, files.values()))
                print(f"{repo_type} {repo_id}@{branch}: {len(files)} files, {size} bytes")
    return 0

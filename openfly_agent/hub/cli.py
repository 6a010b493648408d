"""`python -m openfly_agent.hub {release, release-dataset, fake-hub}`: build release folders and push them."""

from __future__ import annotations

import argparse
import signal
import sys
import time

from openfly_agent.hub.cli_args import add_dataclass_arguments, build_dataclass
from openfly_agent.hub.config import DatasetReleaseConfig, ModelReleaseConfig
from openfly_agent.hub.dataset_release import build_dataset_release
from openfly_agent.hub.fake_hub import FakeHub
from openfly_agent.hub.model_release import build_model_release
from openfly_agent.hub.push import check_push_ready, push_folder
from openfly_agent.utils.logging_utils import setup_logging

PROG = "python -m openfly_agent.hub"
EXAMPLES = {
    "release": (
        f"{PROG} release --checkpoint outputs/train/tiny --repo-id my-user/openfly-agent-tiny "
        "--results outputs/eval                    # writes outputs/releases/openfly-agent-tiny",
        f"HF_HUB_OFFLINE=0 {PROG} release --checkpoint outputs/train/tiny --repo-id my-user/openfly-agent-tiny "
        "--results outputs/eval --overwrite --push",
    ),
    "release-dataset": (
        f"{PROG} release-dataset --dataset-root outputs/datasets/embedded-small --repo-id my-user/openfly-embedded "
        "--card data_cards/embedded.md",
    ),
    "fake-hub": (f'{PROG} fake-hub --token "$HF_TOKEN"      # then HF_ENDPOINT=<printed url> ... --push',),
}


def _epilog(*commands: str) -> str:
    return "examples:\n" + "\n".join(f"  {line}" for name in commands for line in EXAMPLES[name])


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser with one sub-command per release kind."""
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog=PROG, description=__doc__, epilog=_epilog(*EXAMPLES), formatter_class=raw
    )
    commands = parser.add_subparsers(dest="command", required=True)
    model = commands.add_parser(
        "release",
        help="release a model checkpoint (folder, card, optional push)",
        description="Build the release folder of a checkpoint (weights, card, remote code); --push uploads it.",
        epilog=_epilog("release"),
        formatter_class=raw,
    )
    add_dataclass_arguments(model, ModelReleaseConfig)
    dataset = commands.add_parser(
        "release-dataset",
        help="release a generated dataset as a Hub dataset repo",
        description="Build the release folder of a generated dataset (parquet, annotations, card); --push uploads it.",
        epilog=_epilog("release-dataset"),
        formatter_class=raw,
    )
    add_dataclass_arguments(dataset, DatasetReleaseConfig)
    fake = commands.add_parser(
        "fake-hub",
        help="serve a loopback stand-in for the Hub upload API (rehearsal)",
        description="Serve the Hub upload and download endpoints on 127.0.0.1 until Ctrl-C (docs/RELEASE.md).",
        epilog=_epilog("fake-hub"),
        formatter_class=raw,
    )
    fake.add_argument(
        "--token", required=True, help="the token clients must send (use the value of HF_TOKEN)"
    )
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    args = build_parser().parse_args(argv)
    setup_logging()
    try:
        if args.command == "release":
            return _release_model(build_dataclass(ModelReleaseConfig, args))
        if args.command == "release-dataset":
            return _release_dataset(build_dataclass(DatasetReleaseConfig, args))
        return _serve_fake_hub(args.token)
    except (ValueError, OSError, RuntimeError) as err:  # OSError covers missing files and Hub HTTP errors
        print(f"error: {err}", file=sys.stderr)
        return 2


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
        print(f"fake Hub listening: export HF_ENDPOINT={hub.url}  (Ctrl-C to stop)", flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            for (repo_type, repo_id), repo in hub.repos.items():
                for branch, files in repo.branches.items():
                    size = sum(map(len, files.values()))
                    print(f"{repo_type} {repo_id}@{branch}: {len(files)} files, {size} bytes")
    return 0

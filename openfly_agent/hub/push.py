"""Upload a release folder to a Hub model or dataset repo (token from the environment or the login cache)."""

from __future__ import annotations

import logging
from pathlib import Path

logger = logging.getLogger(__name__)

DEFAULT_BRANCH = "main"


class PushError(RuntimeError):
    """The upload cannot start (offline mode, no token, missing folder); the message says what to change."""


def check_push_ready(repo_id: str) -> None:
    """Everything a push needs, checked before the release folder is built: online mode, a token, and a Hub
    that answers and accepts the token (`whoami`). Nothing is written, so a rerun needs no `--overwrite`.

    Raises:
        PushError: offline mode is on, no token is available, the Hub cannot be reached, or it refuses the
            token; one line naming the endpoint and what to change.
    """
    from huggingface_hub import HfApi, constants, get_token
    from huggingface_hub.errors import HfHubHTTPError

    if constants.is_offline_mode():
        raise PushError("HF_HUB_OFFLINE is set: unset HF_HUB_OFFLINE (and TRANSFORMERS_OFFLINE) to push")
    if get_token() is None:
        raise PushError("no Hugging Face token: set HF_TOKEN or run `hf auth login` before pushing")
    endpoint = constants.ENDPOINT
    try:
        user = HfApi().whoami().get("name")
    except HfHubHTTPError as err:  # the Hub answered: the token (or the endpoint) is wrong
        status = err.response.status_code if err.response is not None else "?"
        raise PushError(
            f"the Hub at {endpoint} refused the token (HTTP {status}); check HF_TOKEN / `hf auth login` "
            f"before pushing {repo_id} (nothing was written)"
        ) from None
    except Exception as err:  # no answer at all: network, DNS, proxy, a wrong HF_ENDPOINT
        reason = " ".join(str(err).split()) or type(err).__name__
        raise PushError(
            f"the Hub at {endpoint} cannot be reached ({type(err).__name__}: {reason}); check the network "
            f"or HF_ENDPOINT, then run the same command again (nothing was written)"
        ) from None
    logger.info("pushing to %s as %s", endpoint, user)


def push_folder(
    folder: str | Path,
    repo_id: str,
    *,
    repo_type: str = "model",
    private: bool = False,
    revision: str | None = None,
    commit_message: str = "Upload with openfly-agent",
) -> str:
    """Create `repo_id` if needed, create branch `revision` if needed, upload every file of `folder`.

    The token comes from `HF_TOKEN` or the login cache (`hf auth login`) through huggingface_hub; it is never
    read into our logs. The endpoint is `HF_ENDPOINT` (default huggingface.co).

    Args:
        folder: The release folder written by the release builders.
        repo_id: `namespace/name`.
        repo_type: `model` or `dataset`.
        private: Create the repo private; ignored when it already exists.
        revision: Branch to commit to (created from main when missing); None = main.
        commit_message: Message of the upload commit.

    Returns:
        The URL of the repository (at `revision` when one is given).

    Raises:
        PushError: offline mode is on, no token is available, or `folder` is not a directory.
    """
    from huggingface_hub import HfApi, constants, get_token

    folder = Path(folder)
    if not folder.is_dir():
        raise PushError(f"release folder {folder} does not exist: build it first (without --push=true)")
    if constants.is_offline_mode():
        raise PushError("HF_HUB_OFFLINE is set: unset HF_HUB_OFFLINE (and TRANSFORMERS_OFFLINE) to push")
    if get_token() is None:
        raise PushError("no Hugging Face token: set HF_TOKEN or run `hf auth login` before pushing")
    api = HfApi()  # reads the token itself when sending; we never hold it in a variable we log
    repo_url = api.create_repo(repo_id, repo_type=repo_type, private=private, exist_ok=True)
    logger.info("repository ready: %s", repo_url)
    branch = revision or DEFAULT_BRANCH
    if branch != DEFAULT_BRANCH:
        api.create_branch(repo_id, branch=branch, repo_type=repo_type, exist_ok=True)
    num_files = sum(1 for path in folder.rglob("*") if path.is_file())
    logger.info("uploading %d files from %s to %s@%s", num_files, folder, repo_id, branch)
    commit = api.upload_folder(
        repo_id=repo_id,
        folder_path=folder,
        repo_type=repo_type,
        revision=branch,
        commit_message=commit_message,
    )
    logger.info("commit %s", commit.commit_url)
    return str(repo_url) if branch == DEFAULT_BRANCH else f"{repo_url}/tree/{branch}"

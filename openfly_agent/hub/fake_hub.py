"""A loopback stand-in for the Hub endpoints `huggingface_hub` calls to create a repo and upload a folder.

Used by the tests (and for rehearsing a release offline): point `HF_ENDPOINT` at `FakeHub.url`. It implements
repo creation, branch creation, YAML validation, `preupload` (always answering "regular", so files travel
inline in the commit and no LFS / Xet transfer is needed), the NDJSON `commit` endpoint (base64 contents are
decoded and kept per repo and branch), `repo_info` and `whoami-v2`. Every call must carry the expected token.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import re
import threading
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import unquote, urlsplit

logger = logging.getLogger(__name__)

_REPO_API = re.compile(r"^/api/(?P<type>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)(?P<rest>/.*)?$")


@dataclass
class FakeRepo:
    """One repository: visibility and the files of each branch (path -> bytes), plus the commit log."""

    repo_type: str
    repo_id: str
    private: bool
    branches: dict[str, dict[str, bytes]] = field(default_factory=lambda: {"main": {}})
    commits: list[dict[str, Any]] = field(default_factory=list)


class FakeHub:
    """Threaded HTTP server on 127.0.0.1 with in-memory repos; use as a context manager.

    Args:
        token: The only accepted bearer token; a request without it gets 401.
        user: Name returned by `whoami-v2`.
    """

    def __init__(self, token: str, user: str = "fake-user") -> None:
        self.token = token
        self.user = user
        self.repos: dict[tuple[str, str], FakeRepo] = {}
        self.requests: list[tuple[str, str]] = []  # (method, path) of every request, in order
        self._lock = threading.Lock()
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), _make_handler(self))
        self._thread = threading.Thread(target=self._server.serve_forever, name="fake-hub", daemon=True)

    @property
    def url(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}"

    def __enter__(self) -> FakeHub:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)

    def files(self, repo_id: str, repo_type: str = "model", branch: str = "main") -> dict[str, bytes]:
        """The files currently on `branch` of a repo (KeyError when the repo does not exist)."""
        return dict(self.repos[(repo_type, repo_id)].branches[branch])

    # --- request handling (called from server threads) ------------------------------------------------
    def handle(self, method: str, path: str, headers: dict[str, str], body: bytes) -> tuple[int, dict | None]:
        """Dispatch one request; returns (HTTP status, JSON body)."""
        route = urlsplit(path).path
        with self._lock:
            self.requests.append((method, route))
            if headers.get("authorization") != f"Bearer {self.token}":
                return HTTPStatus.UNAUTHORIZED, {"error": "Invalid credentials in Authorization header"}
            if method == "GET" and route == "/api/whoami-v2":
                return HTTPStatus.OK, {
                    "type": "user",
                    "name": self.user,
                    "auth": {"accessToken": {"role": "write"}},
                }
            if method == "POST" and route == "/api/repos/create":
                return self._create_repo(json.loads(body or b"{}"))
            if method == "POST" and route == "/api/validate-yaml":
                return HTTPStatus.OK, {"errors": [], "warnings": []}
            match = _REPO_API.match(route)
            if match is None:
                return HTTPStatus.NOT_FOUND, {"error": f"fake hub: no route for {method} {route}"}
            repo = self.repos.get((match["type"][:-1], match["repo"]))
            if repo is None:
                return HTTPStatus.NOT_FOUND, {"error": "Repository not found"}
            return self._repo_call(method, repo, match["rest"] or "", body)

    def _create_repo(self, payload: dict) -> tuple[int, dict]:
        repo_type = payload.get("type") or "model"
        repo_id = f"{payload.get('organization') or self.user}/{payload['name']}"
        url = self._repo_url(repo_type, repo_id)
        if (repo_type, repo_id) in self.repos:
            return HTTPStatus.CONFLICT, {"error": "You already created this repo", "url": url}
        private = payload.get("visibility") == "private" or bool(payload.get("private"))
        self.repos[(repo_type, repo_id)] = FakeRepo(repo_type, repo_id, private)
        return HTTPStatus.OK, {"url": url, "name": repo_id}

    def _repo_call(self, method: str, repo: FakeRepo, rest: str, body: bytes) -> tuple[int, dict]:
        parts = [unquote(p) for p in rest.strip("/").split("/")] if rest.strip("/") else []
        if method == "GET" and (not parts or parts[0] == "revision"):
            branch = parts[1] if len(parts) > 1 else "main"
            return self._repo_info(repo, branch)
        if method == "POST" and len(parts) == 2 and parts[0] == "preupload":
            files = json.loads(body)["files"]
            return HTTPStatus.OK, {
                "files": [{"path": f["path"], "uploadMode": "regular", "shouldIgnore": False} for f in files]
            }
        if method == "POST" and len(parts) == 2 and parts[0] == "branch":
            if parts[1] in repo.branches:
                return HTTPStatus.CONFLICT, {"error": f"Branch {parts[1]} already exists"}
            start = (json.loads(body or b"{}") or {}).get("startingPoint") or "main"
            repo.branches[parts[1]] = dict(repo.branches[start])
            return HTTPStatus.OK, {}
        if method == "POST" and len(parts) == 2 and parts[0] == "commit":
            return self._commit(repo, parts[1], body)
        return HTTPStatus.NOT_FOUND, {"error": f"fake hub: no route for {method} {rest}"}

    def _repo_info(self, repo: FakeRepo, branch: str) -> tuple[int, dict]:
        if branch not in repo.branches:
            return HTTPStatus.NOT_FOUND, {"error": f"Invalid rev id: {branch}"}
        sha = repo.commits[-1]["oid"] if repo.commits else "0" * 40
        siblings = [{"rfilename": name} for name in sorted(repo.branches[branch])]
        return HTTPStatus.OK, {"id": repo.repo_id, "sha": sha, "private": repo.private, "siblings": siblings}

    def _commit(self, repo: FakeRepo, branch: str, body: bytes) -> tuple[int, dict]:
        if branch not in repo.branches:
            return HTTPStatus.NOT_FOUND, {"error": f"Invalid rev id: {branch}"}
        lines = [json.loads(line) for line in body.splitlines() if line.strip()]
        if not lines or lines[0].get("key") != "header":
            return HTTPStatus.BAD_REQUEST, {"error": "commit payload must start with a header line"}
        added = {}
        for item in lines[1:]:
            value = item["value"]
            if item["key"] != "file" or value.get("encoding") != "base64":
                return HTTPStatus.BAD_REQUEST, {
                    "error": f"fake hub accepts inline base64 files only, got {item['key']}"
                }
            added[value["path"]] = base64.b64decode(value["content"])
        repo.branches[branch].update(added)
        oid = hashlib.sha1(body).hexdigest()
        repo.commits.append(
            {"oid": oid, "branch": branch, "summary": lines[0]["value"]["summary"], "files": added}
        )
        url = f"{self._repo_url(repo.repo_type, repo.repo_id)}/commit/{oid}"
        return HTTPStatus.OK, {"commitUrl": url, "commitOid": oid, "pullRequestUrl": None}

    def _repo_url(self, repo_type: str, repo_id: str) -> str:
        return f"{self.url}/{repo_id}" if repo_type == "model" else f"{self.url}/{repo_type}s/{repo_id}"


def _make_handler(hub: FakeHub) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def _serve(self) -> None:
            length = int(self.headers.get("content-length") or 0)
            body = self.rfile.read(length) if length else b""
            headers = {k.lower(): v for k, v in self.headers.items()}
            try:
                status, payload = hub.handle(self.command, self.path, headers, body)
            except (KeyError, ValueError) as err:  # malformed request body
                status, payload = HTTPStatus.BAD_REQUEST, {"error": f"fake hub: bad request ({err})"}
            data = json.dumps(payload if payload is not None else {}).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            if status >= 400:
                self.send_header("X-Error-Message", str(payload.get("error", "")) if payload else "")
            self.end_headers()
            self.wfile.write(data)

        do_GET = do_POST = _serve  # noqa: N815 (BaseHTTPRequestHandler naming)

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (signature of the base class)
            logger.debug("fake hub: " + format, *args)

    return Handler

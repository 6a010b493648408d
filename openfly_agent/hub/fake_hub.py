"""A loopback stand-in for the Hub endpoints `huggingface_hub` calls to upload a folder and download files.

Used by the tests (and for rehearsing a release offline): point `HF_ENDPOINT` at `FakeHub.url`. It implements
repo creation, branch creation, YAML validation, `preupload` (always answering "regular", so files travel
inline in the commit and no LFS / Xet transfer is needed), the NDJSON `commit` endpoint (base64 contents are
decoded and kept per repo and branch), `repo_info`, `whoami-v2`, and `resolve` (HEAD / GET of one file at a
branch or commit) so `from_pretrained("<namespace>/<name>")` can read back what was pushed. API calls must
carry the expected token, except reads (downloads, repo info, file lists) of public repos.
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
from urllib.parse import parse_qs, unquote, urlsplit

logger = logging.getLogger(__name__)

_REPO_API = re.compile(r"^/api/(?P<type>models|datasets|spaces)/(?P<repo>[^/]+/[^/]+)(?P<rest>/.*)?$")
_RESOLVE = re.compile(
    r"^/(?:(?P<type>datasets|spaces)/)?(?P<repo>[^/]+/[^/]+)/resolve/(?P<rev>[^/]+)/(?P<path>.+)$"
)
_NO_COMMIT = "0" * 40


@dataclass
class Reply:
    """One HTTP answer: a JSON body or raw bytes, plus extra headers."""

    status: int
    body: dict | list | bytes = field(default_factory=dict)
    headers: dict[str, str] = field(default_factory=dict)


@dataclass
class FakeRepo:
    """One repository: visibility, files per branch (path -> bytes), snapshots per commit, the commit log."""

    repo_type: str
    repo_id: str
    private: bool
    branches: dict[str, dict[str, bytes]] = field(default_factory=lambda: {"main": {}})
    heads: dict[str, str] = field(default_factory=lambda: {"main": _NO_COMMIT})
    snapshots: dict[str, dict[str, bytes]] = field(default_factory=dict)
    commits: list[dict[str, Any]] = field(default_factory=list)


class FakeHub:
    """Threaded HTTP server on 127.0.0.1 with in-memory repos; use as a context manager.

    Args:
        token: The only accepted bearer token; an API request without it gets 401.
        user: Name returned by `whoami-v2`, and the namespace of repos created without one.
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
        """`http://127.0.0.1:<port>`: the value for HF_ENDPOINT."""
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
    def handle(self, method: str, path: str, headers: dict[str, str], body: bytes) -> Reply:
        """Dispatch one request."""
        url = urlsplit(path)
        route = unquote(url.path)
        authorized = headers.get("authorization") == f"Bearer {self.token}"
        with self._lock:
            self.requests.append((method, route))
            download = _RESOLVE.match(route)
            if download is not None and method in ("GET", "HEAD"):
                return self._resolve(download, authorized)
            match = _REPO_API.match(route)
            repo = self.repos.get((match["type"][:-1], match["repo"])) if match else None
            public_read = method == "GET" and repo is not None and not repo.private
            if not (authorized or public_read):
                return Reply(
                    HTTPStatus.UNAUTHORIZED, {"error": "Invalid credentials in Authorization header"}
                )
            if method == "GET" and route == "/api/whoami-v2":
                return Reply(HTTPStatus.OK, {"type": "user", "name": self.user})
            if method == "POST" and route == "/api/repos/create":
                return self._create_repo(json.loads(body or b"{}"))
            if method == "POST" and route == "/api/validate-yaml":
                return Reply(HTTPStatus.OK, {"errors": [], "warnings": []})
            if match is None:
                return Reply(HTTPStatus.NOT_FOUND, {"error": f"fake hub: no route for {method} {route}"})
            if repo is None:
                return _not_found("RepoNotFound", "Repository not found")
            return self._repo_call(method, repo, match["rest"] or "", body, parse_qs(url.query))

    def _create_repo(self, payload: dict) -> Reply:
        repo_type = payload.get("type") or "model"
        repo_id = f"{payload.get('organization') or self.user}/{payload['name']}"
        url = self._repo_url(repo_type, repo_id)
        if (repo_type, repo_id) in self.repos:
            return Reply(HTTPStatus.CONFLICT, {"error": "You already created this repo", "url": url})
        private = payload.get("visibility") == "private" or bool(payload.get("private"))
        self.repos[(repo_type, repo_id)] = FakeRepo(repo_type, repo_id, private)
        return Reply(HTTPStatus.OK, {"url": url, "name": repo_id})

    def _repo_call(self, method: str, repo: FakeRepo, rest: str, body: bytes, query: dict) -> Reply:
        parts = rest.strip("/").split("/") if rest.strip("/") else []
        if method == "GET" and (not parts or parts[0] == "revision"):
            return self._repo_info(repo, parts[1] if len(parts) > 1 else "main")
        if method == "GET" and len(parts) >= 2 and parts[0] == "tree":
            recursive = query.get("recursive", ["false"])[0].lower() == "true"
            return self._tree(repo, parts[1], "/".join(parts[2:]), recursive)
        if method == "POST" and len(parts) == 2 and parts[0] == "preupload":
            files = json.loads(body)["files"]
            modes = [{"path": f["path"], "uploadMode": "regular", "shouldIgnore": False} for f in files]
            return Reply(HTTPStatus.OK, {"files": modes})
        if method == "POST" and len(parts) == 2 and parts[0] == "branch":
            if parts[1] in repo.branches:
                return Reply(HTTPStatus.CONFLICT, {"error": f"Branch {parts[1]} already exists"})
            start = (json.loads(body or b"{}") or {}).get("startingPoint") or "main"
            repo.branches[parts[1]] = dict(repo.branches[start])
            repo.heads[parts[1]] = repo.heads[start]
            return Reply(HTTPStatus.OK, {})
        if method == "POST" and len(parts) == 2 and parts[0] == "commit":
            return self._commit(repo, parts[1], body)
        return Reply(HTTPStatus.NOT_FOUND, {"error": f"fake hub: no route for {method} {rest}"})

    def _snapshot(self, repo: FakeRepo, revision: str) -> tuple[str, dict[str, bytes]] | None:
        """(commit oid, files) of a branch name or a commit oid; None when unknown."""
        if revision in repo.branches:
            return repo.heads[revision], repo.branches[revision]
        if revision in repo.snapshots:
            return revision, repo.snapshots[revision]
        return None

    def _repo_info(self, repo: FakeRepo, revision: str) -> Reply:
        found = self._snapshot(repo, revision)
        if found is None:
            return _not_found("RevisionNotFound", f"Invalid rev id: {revision}")
        sha, files = found
        siblings = [{"rfilename": name} for name in sorted(files)]
        info = {"id": repo.repo_id, "sha": sha, "private": repo.private, "siblings": siblings}
        return Reply(HTTPStatus.OK, info)

    def _tree(self, repo: FakeRepo, revision: str, folder: str, recursive: bool) -> Reply:
        found = self._snapshot(repo, revision)
        if found is None:
            return _not_found("RevisionNotFound", f"Invalid rev id: {revision}")
        prefix = f"{folder.strip('/')}/" if folder.strip("/") else ""
        entries: dict[str, dict] = {}
        for path, content in sorted(found[1].items()):
            if not path.startswith(prefix):
                continue
            parts = path[len(prefix) :].split("/")
            for depth in range(1, len(parts)):  # the folders on the way
                sub = prefix + "/".join(parts[:depth])
                if recursive or depth == 1:
                    entries.setdefault(sub, {"type": "directory", "path": sub, "oid": _NO_COMMIT})
            if recursive or len(parts) == 1:
                oid = hashlib.sha1(content).hexdigest()
                entries[path] = {"type": "file", "path": path, "size": len(content), "oid": oid}
        if prefix and not entries:
            return _not_found("EntryNotFound", f"{folder} does not exist on {revision}")
        return Reply(HTTPStatus.OK, list(entries.values()))

    def _commit(self, repo: FakeRepo, branch: str, body: bytes) -> Reply:
        if branch not in repo.branches:
            return _not_found("RevisionNotFound", f"Invalid rev id: {branch}")
        lines = [json.loads(line) for line in body.splitlines() if line.strip()]
        if not lines or lines[0].get("key") != "header":
            return Reply(HTTPStatus.BAD_REQUEST, {"error": "commit payload must start with a header line"})
        added = {}
        for item in lines[1:]:
            value = item["value"]
            if item["key"] != "file" or value.get("encoding") != "base64":
                error = f"fake hub accepts inline base64 files only, got {item['key']}"
                return Reply(HTTPStatus.BAD_REQUEST, {"error": error})
            added[value["path"]] = base64.b64decode(value["content"])
        repo.branches[branch].update(added)
        oid = hashlib.sha1(repo.heads[branch].encode() + body).hexdigest()
        repo.heads[branch] = oid
        repo.snapshots[oid] = dict(repo.branches[branch])
        summary = lines[0]["value"]["summary"]
        repo.commits.append({"oid": oid, "branch": branch, "summary": summary, "files": added})
        url = f"{self._repo_url(repo.repo_type, repo.repo_id)}/commit/{oid}"
        return Reply(HTTPStatus.OK, {"commitUrl": url, "commitOid": oid, "pullRequestUrl": None})

    def _resolve(self, match: re.Match, authorized: bool) -> Reply:
        repo = self.repos.get(((match["type"] or "models")[:-1], match["repo"]))
        if repo is None or (repo.private and not authorized):
            return _not_found("RepoNotFound", "Repository not found")
        found = self._snapshot(repo, match["rev"])
        if found is None:
            return _not_found("RevisionNotFound", f"Invalid rev id: {match['rev']}")
        sha, files = found
        if match["path"] not in files:
            return _not_found("EntryNotFound", f"{match['path']} does not exist on {match['rev']}")
        content = files[match["path"]]
        etag = f'"{hashlib.sha256(content).hexdigest()}"'
        return Reply(HTTPStatus.OK, content, {"X-Repo-Commit": sha, "ETag": etag})

    def _repo_url(self, repo_type: str, repo_id: str) -> str:
        return f"{self.url}/{repo_id}" if repo_type == "model" else f"{self.url}/{repo_type}s/{repo_id}"


def _not_found(code: str, message: str) -> Reply:
    return Reply(HTTPStatus.NOT_FOUND, {"error": message}, {"X-Error-Code": code, "X-Error-Message": message})


def _make_handler(hub: FakeHub) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def _serve(self) -> None:
            length = int(self.headers.get("content-length") or 0)
            body = self.rfile.read(length) if length else b""
            headers = {k.lower(): v for k, v in self.headers.items()}
            try:
                reply = hub.handle(self.command, self.path, headers, body)
            except (KeyError, ValueError) as err:  # malformed request body
                reply = Reply(HTTPStatus.BAD_REQUEST, {"error": f"fake hub: bad request ({err})"})
            raw = reply.body if isinstance(reply.body, bytes) else json.dumps(reply.body).encode()
            self.send_response(reply.status)
            content_type = "application/octet-stream" if isinstance(reply.body, bytes) else "application/json"
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(raw)))
            for name, value in reply.headers.items():
                self.send_header(name, value)
            if (
                reply.status >= 400
                and isinstance(reply.body, dict)
                and "X-Error-Message" not in reply.headers
            ):
                self.send_header("X-Error-Message", str(reply.body.get("error", "")))
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(raw)

        do_GET = do_POST = do_HEAD = _serve  # noqa: N815 (BaseHTTPRequestHandler naming)

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (signature of the base class)
            logger.debug("fake hub: " + format, *args)

    return Handler

"""The OpenAI-compatible VLM backend against a fake chat-completions server on 127.0.0.1."""

from __future__ import annotations

import base64
import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import cv2
import numpy as np
import pytest
from toolchain_scene import synthetic_scene

from openfly_agent.toolchain.config import InstructionConfig, VLMConfig
from openfly_agent.toolchain.instructions import (
    InstructionRequest,
    VLMError,
    VLMInstructionBackend,
    make_instruction_backend,
    prompts,
)

KEY = "sk-test-not-a-real-key"


class FakeChatServer:
    """Records every request; fails the first `fail_first` with HTTP 500; checks the bearer key."""

    def __init__(self, fail_first: int = 0):
        self.requests: list[dict] = []
        self.fail_first = fail_first
        self.lock = threading.Lock()
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # keep pytest output clean
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                with outer.lock:
                    outer.requests.append(
                        {"path": self.path, "auth": self.headers.get("Authorization"), "body": body}
                    )
                    failing = outer.fail_first > 0
                    outer.fail_first -= 1
                if failing:
                    self.send_response(500)
                    self.end_headers()
                    return
                if self.headers.get("Authorization") != f"Bearer {KEY}":
                    self._reply(401, {"error": {"message": "bad key"}})
                    return
                system = body["messages"][0]["content"]
                if system == prompts.FUSION_SYSTEM:
                    content = "Fly past the green hall, then stop at the red tower."
                elif system == prompts.TARGET_SYSTEM:
                    content = 'Sure: {"color": "red", "feature": "spire", "size": "tall", "type": "tower"}'
                else:
                    content = '{"color": "green", "feature": "flat roof", "size": "low", "type": "hall"}'
                self._reply(200, {"choices": [{"message": {"role": "assistant", "content": content}}]})

            def _reply(self, code, payload):
                data = json.dumps(payload).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.server.server_address[1]}/v1"

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()
        self.thread.join(timeout=5)


def _request(seed=0):
    landmarks = {lm.landmark_id: lm for lm in synthetic_scene()[1]}
    actions = np.array([3, 9, 9, 2, 9, 0])  # right | forward | left | forward -> 3 intermediate ends + target
    frames = [np.full((32, 48, 3), 40 * t, np.uint8) for t in range(len(actions))]
    boxes = [{} for _ in actions]
    boxes[5] = {"b0": np.array([0.8, 0.5, 0.2, 0.4])}  # the target on the right of the last frame
    return InstructionRequest(actions, boxes, landmarks, ["b0"], [5], seed=seed, frames=frames)


def _decode(url: str) -> np.ndarray:
    assert url.startswith("data:image/png;base64,")
    png = np.frombuffer(base64.b64decode(url.split(",", 1)[1]), np.uint8)
    return cv2.cvtColor(cv2.imdecode(png, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def _cfg(server, **kw):
    return VLMConfig(
        base_url=server.base_url,
        model="fake-vlm",
        api_key_env="OPENFLY_TEST_VLM_KEY",
        backoff_s=0.01,
        timeout_s=5,
        **kw,
    )


def test_vlm_backend_sends_both_prompts_and_three_images(monkeypatch):
    monkeypatch.setenv("OPENFLY_TEST_VLM_KEY", KEY)
    with FakeChatServer() as server:
        backend = make_instruction_backend(InstructionConfig(backend="vlm", vlm=_cfg(server)))
        texts = backend.generate([_request()])
    assert texts == ["Fly past the green hall, then stop at the red tower."]
    reqs = server.requests
    assert all(r["path"] == "/v1/chat/completions" and r["auth"] == f"Bearer {KEY}" for r in reqs)
    assert all(r["body"]["model"] == "fake-vlm" for r in reqs)
    systems = [r["body"]["messages"][0]["content"] for r in reqs]
    assert systems == [prompts.LANDMARK_SYSTEM] * 3 + [prompts.TARGET_SYSTEM, prompts.FUSION_SYSTEM]

    def images(r):
        return [
            p["image_url"]["url"] for p in r["body"]["messages"][1]["content"] if p["type"] == "image_url"
        ]

    assert [len(images(r)) for r in reqs] == [1, 1, 1, 3, 0]
    # intermediate calls see the frame where each sub-trajectory ends (1, 3, 4); the target call frames 3..5
    assert [int(_decode(images(r)[0])[0, 0, 0]) for r in reqs[:3]] == [40, 120, 160]
    assert [int(_decode(u)[0, 0, 0]) for u in images(reqs[3])] == [120, 160, 200]
    target_text = reqs[3]["body"]["messages"][1]["content"][0]["text"]
    assert "at the right of the last image" in target_text
    fusion_text = reqs[4]["body"]["messages"][1]["content"][0]["text"]
    assert fusion_text.count('"type": "hall"') == 3 and '"type": "tower"' in fusion_text
    assert fusion_text.splitlines()[1].startswith("1. ") and len(fusion_text.splitlines()) == 5


def test_vlm_retries_server_errors_then_succeeds(monkeypatch):
    monkeypatch.setenv("OPENFLY_TEST_VLM_KEY", KEY)
    with FakeChatServer(fail_first=2) as server:
        backend = VLMInstructionBackend(_cfg(server, max_retries=3))
        assert backend.generate([_request()])[0].startswith("Fly past")
    assert len(server.requests) == 5 + 2


def test_vlm_gives_up_after_retries_and_reports_none(monkeypatch, caplog):
    monkeypatch.setenv("OPENFLY_TEST_VLM_KEY", KEY)
    with FakeChatServer(fail_first=100) as server:
        backend = VLMInstructionBackend(_cfg(server, max_retries=1))
        assert backend.generate([_request()]) == [None]
    assert len(server.requests) == 2  # first try + 1 retry of the first call, then the request is dropped
    assert KEY not in caplog.text


def test_vlm_auth_error_is_not_retried_and_key_is_not_logged(monkeypatch, caplog):
    monkeypatch.setenv("OPENFLY_TEST_VLM_KEY", "sk-wrong")
    with FakeChatServer() as server:
        backend = VLMInstructionBackend(_cfg(server))
        with pytest.raises(VLMError, match="HTTP 401") as err:
            backend.instruction(_request())
    assert len(server.requests) == 1
    assert "sk-wrong" not in str(err.value) and "sk-wrong" not in caplog.text


def test_missing_key_names_the_variable(monkeypatch):
    monkeypatch.delenv("OPENFLY_TEST_VLM_KEY", raising=False)
    with pytest.raises(VLMError, match="OPENFLY_TEST_VLM_KEY"):
        VLMInstructionBackend(VLMConfig(api_key_env="OPENFLY_TEST_VLM_KEY"))


def test_concurrent_requests_all_complete(monkeypatch):
    monkeypatch.setenv("OPENFLY_TEST_VLM_KEY", KEY)
    with FakeChatServer() as server:
        backend = VLMInstructionBackend(_cfg(server, concurrency=4))
        texts = backend.generate([_request(seed=s) for s in range(6)])
    assert len(texts) == 6 and all(t for t in texts)
    assert len(server.requests) == 6 * 5


def test_landmark_json_parsing():
    assert prompts.parse_landmark_json('x {"color": "red", "type": "tower", "extra": 1} y') == {
        "color": "red",
        "type": "tower",
    }
    with pytest.raises(ValueError):
        prompts.parse_landmark_json("no json here")

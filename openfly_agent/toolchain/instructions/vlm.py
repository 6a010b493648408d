"""OpenAI-compatible VLM backend: the paper's landmark and fusion prompts over `/v1/chat/completions`.

Stdlib HTTP only (urllib). Frames go as base64 PNG data URLs; requests run on a bounded thread pool
(`concurrency`), each call retried with exponential backoff on 429 / 5xx / network errors. The API key is
read from the environment variable named in the config and never logged.
"""

from __future__ import annotations

import base64
import json
import logging
import os
import time
import urllib.error
import urllib.request
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from openfly_agent.toolchain.config import VLMConfig
from openfly_agent.toolchain.instructions import prompts
from openfly_agent.toolchain.instructions.segments import (
    LANDING,
    TAKEOFF,
    InstructionRequest,
    image_side,
    merge_short_segments,
    split_at_transitions,
)
from openfly_agent.toolchain.instructions.template import action_phrase

logger = logging.getLogger(__name__)


class VLMError(RuntimeError):
    """A request that failed for good (non-retryable status, or retries exhausted)."""


class _Retryable(Exception):
    pass


def image_data_url(rgb: np.ndarray, max_side: int) -> str:
    """(H, W, 3) uint8 RGB -> 'data:image/png;base64,...', longest side resized to at most `max_side`."""
    h, w = rgb.shape[:2]
    scale = min(1.0, max_side / max(h, w))
    if scale < 1.0:
        rgb = cv2.resize(
            rgb, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA
        )
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("PNG encoding of a frame failed")
    return "data:image/png;base64," + base64.b64encode(png.tobytes()).decode("ascii")


class ChatClient:
    """Minimal `/chat/completions` client with retries; thread-safe (no shared connection state)."""

    def __init__(self, cfg: VLMConfig, api_key: str | None = None):
        self.cfg = cfg
        key = api_key if api_key is not None else os.environ.get(cfg.api_key_env)
        if not key:
            raise VLMError(
                f"the VLM backend needs an API key: set the environment variable {cfg.api_key_env}"
            )
        self._headers = {"Content-Type": "application/json", "Authorization": f"Bearer {key}"}
        self.url = cfg.base_url.rstrip("/") + "/chat/completions"

    def complete(self, system: str, text: str, images: list[np.ndarray] = ()) -> str:
        """One chat completion: system prompt, then a user message with `text` and the images."""
        content = [{"type": "text", "text": text}]
        content += [
            {"type": "image_url", "image_url": {"url": image_data_url(im, self.cfg.image_size)}}
            for im in images
        ]
        payload = {
            "model": self.cfg.model,
            "messages": [{"role": "system", "content": system}, {"role": "user", "content": content}],
            "temperature": self.cfg.temperature,
            "max_tokens": self.cfg.max_tokens,
        }
        body = json.dumps(payload).encode("utf-8")
        for attempt in range(self.cfg.max_retries + 1):
            try:
                return self._post(body)
            except _Retryable as err:
                if attempt == self.cfg.max_retries:
                    raise VLMError(f"{self.url}: giving up after {attempt + 1} tries: {err}") from None
                delay = self.cfg.backoff_s * (2**attempt)
                logger.warning("VLM request failed (%s); retry %d in %.1f s", err, attempt + 1, delay)
                time.sleep(delay)
        raise AssertionError("unreachable")

    def _post(self, body: bytes) -> str:
        request = urllib.request.Request(self.url, data=body, headers=self._headers, method="POST")
        try:
            with urllib.request.urlopen(request, timeout=self.cfg.timeout_s) as response:
                reply = json.loads(response.read().decode("utf-8"))
        except urllib.error.HTTPError as err:
            detail = err.read()[:200].decode("utf-8", "replace")
            if err.code == 429 or err.code >= 500:
                raise _Retryable(f"HTTP {err.code}") from None
            raise VLMError(f"{self.url}: HTTP {err.code}: {detail}") from None
        except (urllib.error.URLError, TimeoutError, ConnectionError, json.JSONDecodeError) as err:
            raise _Retryable(type(err).__name__ + ": " + str(err)) from None
        try:
            content = reply["choices"][0]["message"]["content"]
        except (KeyError, IndexError, TypeError):
            raise VLMError(
                f"{self.url}: reply without choices[0].message.content: {str(reply)[:200]}"
            ) from None
        if isinstance(content, list):  # content parts
            content = "".join(part.get("text", "") for part in content if isinstance(part, dict))
        return str(content).strip()


class VLMInstructionBackend:
    """Landmark call per sub-trajectory end, target call on the last 3 frames, then the fusion call."""

    def __init__(self, cfg: VLMConfig, client: ChatClient | None = None):
        self.cfg = cfg
        self.client = client or ChatClient(cfg)

    def _landmark(self, frame: np.ndarray) -> dict | None:
        reply = self.client.complete(prompts.LANDMARK_SYSTEM, prompts.landmark_user_text(), [frame])
        try:
            return prompts.parse_landmark_json(reply)
        except ValueError as err:
            logger.warning("landmark reply ignored: %s", err)
            return None

    def instruction(self, request: InstructionRequest) -> str:
        """The instruction of one trajectory (raises VLMError when a call fails for good)."""
        if request.frames is None:
            raise ValueError("the VLM backend needs the rendered frames in InstructionRequest.frames")
        rng = np.random.default_rng(request.seed)
        segments = merge_short_segments(split_at_transitions(request.actions), request.merge_short_m)
        nav = [s for s in segments if s.kind not in (TAKEOFF, LANDING)]
        stop_frame = request.leg_end_frames[-1]
        items: list[tuple[str, dict | None]] = []
        for seg in nav[:-1]:
            frame = request.frames[min(seg.end, len(request.frames) - 1)]
            items.append((action_phrase(seg, rng, mention_distance=True), self._landmark(frame)))
        last3 = request.frames[max(0, stop_frame - 2) : stop_frame + 1]
        box = request.frame_boxes[stop_frame].get(request.target_ids[-1])
        reply = self.client.complete(prompts.TARGET_SYSTEM, prompts.target_user_text(image_side(box)), last3)
        try:
            target = prompts.parse_landmark_json(reply)
        except ValueError as err:
            raise VLMError(f"target landmark reply unusable: {err}") from None
        phrase = action_phrase(nav[-1], rng, mention_distance=True) if nav else "stop"
        items.append((phrase, target))
        return self.client.complete(prompts.FUSION_SYSTEM, prompts.fusion_user_text(items))

    def generate(self, requests: list[InstructionRequest]) -> list[str | None]:
        """Instructions of many trajectories, `concurrency` at a time; None (logged) where one failed."""

        def one(request: InstructionRequest) -> str | None:
            try:
                return self.instruction(request)
            except VLMError as err:
                logger.error("instruction failed: %s", err)
                return None

        with ThreadPoolExecutor(max_workers=self.cfg.concurrency) as pool:
            return list(pool.map(one, requests))

    def close(self) -> None:
        pass

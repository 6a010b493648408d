"""`StepTimer`: where a training step's time goes (data wait, forward, backward, optimizer, the rest), its
model FLOPs and its MFU, reported at the log steps.

The loop marks the end of each phase (`end("forward")`, ...) and iterates its batches through `batches`, which
marks the data wait. A mark is a CUDA event on a GPU (recorded on the stream: no synchronisation; the report
synchronises once, at a log step) and the wall clock on the CPU. A phase's time is the time between its mark
and the one before, so the phases of an interval add up to the whole interval: `other` is what follows the
optimizer (the scheduler, the weight average, logging, validation, checkpoints) until the next batch is asked
for. On a GPU the times are the GPU's timeline: a data wait the GPU did not notice (it was still busy) counts
as 0, and the host-side launch time hides inside the GPU's phases.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator
from typing import Any

import torch

from openfly_agent.training.throughput import StepFlops, mfu

logger = logging.getLogger(__name__)

PHASES = ("data", "forward", "backward", "optimizer", "other")


class StepTimer:
    """Per-phase times, model FLOPs and MFU of the optimizer steps between two reports.

    Args:
        device: the training device (CUDA: events; else the wall clock).
        step_flops: the model-FLOP count of the agent (None: no FLOPs, no MFU).
        peak_flops: the device's peak FLOP/s (None: no MFU, e.g. on the CPU).
    """

    def __init__(
        self, device: torch.device, step_flops: StepFlops | None = None, peak_flops: float | None = None
    ) -> None:
        self._cuda = torch.device(device).type == "cuda"
        self._step_flops = step_flops
        self._peak = peak_flops
        self._marks: list[tuple[str, Any]] = [("start", self._mark())]
        self._flops: torch.Tensor | float = 0.0
        self._steps = 0

    def _mark(self) -> Any:
        if not self._cuda:
            return time.perf_counter()
        event = torch.cuda.Event(enable_timing=True)
        event.record()
        return event

    def end(self, phase: str) -> None:
        """The time since the previous mark was spent in `phase` (one of `PHASES`)."""
        self._marks.append((phase, self._mark()))

    def batches(self, batches: Iterable) -> Iterator:
        """`batches`, with the wait for each one marked as `data` (and what came before it as `other`)."""
        iterator = iter(batches)
        while True:
            self.end("other")
            try:
                batch = next(iterator)
            except StopIteration:
                return
            self.end("data")
            yield batch

    def count(self, batch: dict) -> None:
        """Add the model FLOPs of one micro-batch (kept on its device until the report)."""
        if self._step_flops is not None:
            self._flops = self._flops + self._step_flops.batch_flops(batch)

    def step_done(self) -> None:
        """One optimizer step ended."""
        self._steps += 1

    def report(self, accelerator=None) -> dict[str, float]:
        """Seconds per optimizer step of each phase (`time/<phase>_s`) and in all (`time/step_s`), the model
        TFLOP/s (`throughput/tflops`) and `throughput/mfu` (absent without a peak) since the last report; then
        reset.

        With an `accelerator` of several processes, every process must call this at the same step: FLOPs are
        summed over the processes and MFU is against the peak of all their devices.
        """
        self.end("other")
        if self._cuda:
            self._marks[-1][1].synchronize()
        seconds = dict.fromkeys(PHASES, 0.0)
        for (_, before), (phase, after) in zip(self._marks, self._marks[1:]):
            seconds[phase] += before.elapsed_time(after) / 1e3 if self._cuda else after - before
        steps = max(self._steps, 1)
        total = sum(seconds.values())
        out = {f"time/{phase}_s": value / steps for phase, value in seconds.items()}
        out["time/step_s"] = total / steps
        if self._step_flops is not None:
            flops = torch.as_tensor(self._flops, dtype=torch.float64)
            processes = 1
            if accelerator is not None and accelerator.num_processes > 1:
                processes = accelerator.num_processes
                flops = accelerator.reduce(flops.to(accelerator.device), reduction="sum")
            flops = float(flops)
            out["throughput/tflops"] = flops / max(total, 1e-9) / processes / 1e12  # per device
            utilisation = mfu(flops, total * processes, self._peak)
            if utilisation is not None:
                out["throughput/mfu"] = utilisation
        self._marks = [self._marks[-1]]
        self._flops, self._steps = 0.0, 0
        return out


def log_line(step: int, figures: dict[str, float], tokens_per_s: float | None = None) -> str:
    """The log line of a `StepTimer.report`: seconds per step and its split, tokens/s, TFLOP/s and MFU."""
    split = ", ".join(f"{phase} {figures[f'time/{phase}_s']:.4f}" for phase in PHASES)
    parts = [f"step {step} time: {figures['time/step_s']:.4f} s per step ({split})"]
    if tokens_per_s is not None:
        parts.append(f"{tokens_per_s:.0f} tokens/s")
    if "throughput/tflops" in figures:
        parts.append(f"{figures['throughput/tflops']:.3g} model TFLOP/s per device")
    mfu_value = figures.get("throughput/mfu")
    parts.append(
        f"MFU {mfu_value:.3f}" if mfu_value is not None else "MFU n/a (no peak known for this device)"
    )
    return "; ".join(parts)

"""The long-running scripts pass a stop on to their recipe (scripts/_child.sh): a SIGTERM or Ctrl-C sent to the
script alone reaches the recipe as SIGTERM, the script waits for it and exits with its status, and runs nothing
after it. A stand-in for the venv's python announces itself on stdout and waits for a signal; the test signals
the script only after reading that line, so the signal lands while the recipe runs, however slow the machine."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from openfly_agent.utils.config import REPO_ROOT

STAND_IN = """\
import os, signal, sys
log = {log!r}
def stop(signum, frame):
    with open(log, "a") as f:
        f.write(f"stopped by {{signal.Signals(signum).name}}\\n")
    sys.exit(143)
signal.signal(signal.SIGTERM, stop)
with open(log, "a") as f:
    f.write(f"started {{os.getpid()}} " + " ".join(sys.argv[1:]) + "\\n")
print("stand-in: running", flush=True)
while True:
    signal.pause()
"""


def _stand_in_venv(tmp_path):
    """A VENV whose bin/python logs its start, prints one line, and on SIGTERM logs it and exits 143."""
    log = tmp_path / "calls.txt"
    python = tmp_path / "venv" / "bin" / "python"
    python.parent.mkdir(parents=True)
    python.write_text(f"#!{sys.executable}\n" + STAND_IN.format(log=str(log)))
    python.chmod(0o755)
    return tmp_path / "venv", log


def _as_from_a_terminal() -> None:
    """SIGINT as a shell started from a terminal has it: a test run started in the background (`pytest &`) ignores
    SIGINT, and a non-interactive bash that starts with SIGINT ignored cannot trap it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(script: str, env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        ["bash", str(REPO_ROOT / "scripts" / script)],
        env={**os.environ, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        preexec_fn=_as_from_a_terminal,
    )


def _stop_once_the_recipe_runs(script: subprocess.Popen, signum: int, log) -> tuple[list[str], str]:
    """Signal the script once its recipe runs; its exit status, and the stand-in's log lines, after it exits."""
    line = script.stdout.readline()  # the event: the stand-in recipe is running
    assert line == "stand-in: running\n", line
    recipe_pid = int(log.read_text().split()[1])
    try:
        script.send_signal(signum)
        script.wait(timeout=120)
        alive = _alive(recipe_pid)
    finally:
        if _alive(recipe_pid):  # a script that died alone left its recipe running: end it, then fail
            os.kill(recipe_pid, signal.SIGKILL)
        if script.poll() is None:  # a script that did not stop (the test fails): end it too
            script.kill()
            script.wait()
    assert not alive, "the script exited and left its recipe running"
    return log.read_text().splitlines(), script.stdout.read()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_stopping_the_main_job_script_stops_its_recipe_and_reports_the_stop(tmp_path, signum):
    venv, log = _stand_in_venv(tmp_path)
    script = _start("main_job.sh", {"VENV": str(venv), "SKIP_SETUP": "1", "RUN": str(tmp_path / "run")})
    calls, after = _stop_once_the_recipe_runs(script, signum, log)
    assert calls[0].split()[2:4] == ["-m", "openfly_agent.recipe"]
    assert calls[1:] == [
        "stopped by SIGTERM"
    ]  # Ctrl-C reaches the recipe as SIGTERM too: one way to stop a stage
    assert script.returncode == 143
    assert "done" not in after  # the script stops with its recipe: no "done. Table:" line


def test_stopping_the_long_ablations_script_starts_no_further_arm(tmp_path):
    venv, log = _stand_in_venv(tmp_path)
    env = {"VENV": str(venv), "ROOT": str(tmp_path / "abl"), "ARMS": "current_frame keyframes"}
    script = _start("long_ablations.sh", env)
    calls, _ = _stop_once_the_recipe_runs(script, signal.SIGTERM, log)
    assert len(calls) == 2 and "keyframes_merging.yaml" in calls[0] and calls[1] == "stopped by SIGTERM"
    assert script.returncode == 143

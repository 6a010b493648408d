"""The commands and Python snippets of README.md, docs/*.md and docs/experiments/*.md, found and sorted for
tests/test_docs.py.

Commands come from ```bash fenced blocks (continuation lines joined, comments dropped) and from inline code
spans that start with an entry point (`python eval.py ...`). Each is resolved to its entry point (train.py,
eval.py, the toolchain, hub and simulator commands, bench/ and scripts/ files) and its options are checked
against that entry point's real parser; those that can run on a CPU without a GPU, a real engine, the
network or a 7B model are also executed on small data.
"""

from __future__ import annotations

import re
import shlex
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOC_FILES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
# The experiment log (dated entries, appended, never rewritten): its commands are historical, so their options
# are checked against today's parsers but its blocks are not run (tests/test_docs.py, HISTORICAL).
HISTORICAL = REPO / "docs" / "experiments"
DOC_FILES += sorted(HISTORICAL.glob("*.md"))
ENTRY_WORDS = ("python ", "python3 ", "accelerate launch", "torchrun ", "openfly-generate", "openfly-hub")
ENTRY_WORDS += ("bash scripts/", "train.py ", "eval.py ")
PLACEHOLDER = re.compile(r"<[^>]*>|\$|\.\.\.|\*")
# What cannot run here: GPU launcher files and presets, real engines, the Hub, long jobs.
NOT_ON_CPU = (
    "single_gpu.yaml", "ddp.yaml", "fsdp", "deepspeed", "openfly-7b", "openvla", "released-", "--push",
    "unrealcv", "airsim", "gs_http", "embedded-100k", "main_job.sh", "--multi_gpu", "--nnodes",
    "openfly_agent.recipe",  # the recipe: 30 min to 3 h (its parts run in tests/recipe and here one by one)
)  # fmt: skip
LAUNCHER_OPTIONS_WITH_VALUE = {
    "--config_file", "--num_processes", "--num_machines", "--machine_rank", "--main_process_ip",
    "--main_process_port", "--mixed_precision", "--dynamo_backend", "--nproc_per_node", "--nnodes",
    "--node_rank", "--rdzv_endpoint", "--num_cpu_threads_per_process",
}  # fmt: skip


@dataclass
class DocCommand:
    """One documented command line."""

    file: str  # relative to the repository
    line: int
    text: str  # as written (continuations joined)
    env: dict[str, str] = field(default_factory=dict)
    kind: str = (
        "other"  # train | eval | toolchain | hub | sim | recipe | compare | seeds | script | shell | other
    )
    sub: str | None = None  # toolchain / hub / sim sub-command, or the script path
    args: list[str] = field(default_factory=list)  # the entry point's own arguments
    launcher: list[str] = field(default_factory=list)  # accelerate / torchrun part, when there is one
    block: int | None = None  # index of its fenced block in the file (None: an inline code span)

    @property
    def where(self) -> str:
        return f"{self.file}:{self.line}: {self.text}"

    @property
    def has_placeholders(self) -> bool:
        return any(PLACEHOLDER.search(token) for token in self.args + self.launcher)

    @property
    def runs_on_cpu(self) -> bool:
        """No placeholder, no GPU / engine / Hub / 7B / hours-long job in it."""
        return (
            not self.has_placeholders
            and "..." not in self.text
            and not any(w in self.text for w in NOT_ON_CPU)
        )


@dataclass
class DocSnippet:
    """One ```python block."""

    file: str
    line: int
    code: str

    @property
    def where(self) -> str:
        return f"{self.file}:{self.line}"


def _relative(path: Path) -> str:
    return str(path.relative_to(REPO))


def _shell_lines(body: str, first_line: int) -> list[tuple[int, str]]:
    """Logical lines of a shell block (continuations joined), with their line numbers."""
    out, pending, start = [], "", first_line
    for offset, raw in enumerate(body.splitlines()):
        line = raw.rstrip()
        if not pending:
            start = first_line + offset
        if line.endswith("\\"):
            pending += line[:-1] + " "
            continue
        text = (pending + line).strip()
        pending = ""
        if text and not text.startswith("#"):
            out.append((start, text))
    return out


def _tokens(text: str) -> list[str]:
    text = re.sub(r"<[^>]*>", "<x>", text)  # a placeholder is one value, whatever it says
    try:
        tokens = shlex.split(text, comments=True)
    except ValueError:  # an unbalanced quote in prose: split on blanks
        tokens = text.split()
    cleaned = []
    for token in tokens:
        if token.startswith("[") and token.endswith("]") and "=" not in token:  # `[--flag]`: optional
            token = token[1:-1]
        while token.startswith("[") and token.count("[") > token.count("]"):  # `[--flag value]` split
            token = token[1:]
        while token.endswith("]") and token.count("]") > token.count("["):  # keeps `--roots=[a,b]`
            token = token[:-1]
        if token and token not in ("...", "|"):
            cleaned.append(token)
    return cleaned


def parse_command(file: str, line: int, text: str, block: int | None = None) -> DocCommand:
    """Resolve `text` to its entry point and arguments."""
    command = DocCommand(file, line, text, block=block)
    tokens = _tokens(text)
    while tokens and (re.match(r"^[A-Z_][A-Z0-9_]*=", tokens[0]) or tokens[0] in ("env", "nice")):
        if tokens[0] == "nice":
            tokens = tokens[3:] if tokens[1:2] == ["-n"] else tokens[1:]
            continue
        if tokens[0] != "env":
            key, _, value = tokens[0].partition("=")
            command.env[key] = value
        tokens = tokens[1:]
    if not tokens:
        return command
    start = None
    if tokens[:2] == ["accelerate", "launch"]:
        start = 2
    elif tokens[0] == "torchrun":
        start = 1
    elif tokens[1:3] == ["-m", "torch.distributed.run"]:
        start = 3
    if start is not None:
        i = start
        while i < len(tokens) and not tokens[i].endswith(".py"):
            i += 2 if tokens[i] in LAUNCHER_OPTIONS_WITH_VALUE else 1
        command.launcher, tokens = tokens[:i], tokens[i:]
    if tokens and tokens[0] in ("python", "python3") and len(tokens) > 1:
        if tokens[1] == "-m" and len(tokens) > 2:
            module, rest = tokens[2], tokens[3:]
            kinds = {
                "openfly_agent.toolchain": "toolchain",
                "openfly_agent.hub": "hub",
                "openfly_agent.sim.cli": "sim",
                "openfly_agent.recipe": "recipe",
                "openfly_agent.eval.compare": "compare",
                "openfly_agent.eval.seeds": "seeds",
            }
            if module in kinds:
                command.kind = kinds[module]
                if (
                    command.kind not in ("recipe", "compare", "seeds")
                    and rest
                    and not rest[0].startswith("-")
                ):
                    command.sub, rest = (rest[0], rest[1:]) if rest else (None, [])
                command.args = rest
            return command
        if tokens[1] == "-c":
            return command
        tokens = tokens[1:]
    if tokens and tokens[0] in ("openfly-generate", "openfly-hub"):
        command.kind = "toolchain" if tokens[0] == "openfly-generate" else "hub"
        command.sub, command.args = (tokens[1], tokens[2:]) if len(tokens) > 1 else (None, [])
        return command
    if tokens and tokens[0] == "bash" and len(tokens) > 1:
        command.kind, command.sub, command.args = "shell", tokens[1], tokens[2:]
        return command
    if tokens and tokens[0].endswith(".py"):
        name = tokens[0]
        command.kind = {"train.py": "train", "eval.py": "eval"}.get(name, "script")
        command.sub, command.args = name, tokens[1:]
    return command


def doc_commands() -> list[DocCommand]:
    """Every command of README.md and docs/*.md: fenced shell blocks, then inline code spans."""
    found = []
    for path in DOC_FILES:
        text = path.read_text()
        for block, match in enumerate(re.finditer(r"```(bash|sh|shell)\n(.*?)```", text, re.S)):
            first = text.count("\n", 0, match.start(2)) + 1
            lines = _shell_lines(match.group(2), first)
            found += [parse_command(_relative(path), n, t, block) for n, t in lines]
        prose = re.sub(r"```.*?```", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S)
        for match in re.finditer(r"`([^`]+)`", prose):
            span = " ".join(match.group(1).split())
            is_message = any(word.endswith(":") for word in span.split()[:5])  # `train.py: ...` is output
            if span.startswith(ENTRY_WORDS) and not is_message:
                found.append(parse_command(_relative(path), prose.count("\n", 0, match.start()) + 1, span))
    return found


def doc_snippets() -> list[DocSnippet]:
    """Every ```python block of README.md and docs/*.md."""
    snippets = []
    for path in DOC_FILES:
        text = path.read_text()
        for match in re.finditer(r"```python\n(.*?)```", text, re.S):
            line = text.count("\n", 0, match.start(1)) + 1
            snippets.append(DocSnippet(_relative(path), line, textwrap.dedent(match.group(1))))
    return snippets

"""Progress bars written to a log end at 100 % (issue 48): utils/progress.py, the package's only tqdm."""

from __future__ import annotations

import io
import re
from pathlib import Path

from openfly_agent.utils.progress import progress_bar

PACKAGE = Path(__file__).resolve().parents[2] / "openfly_agent"


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def _last_draw(stream: io.StringIO) -> str:
    """The bar as the stream shows it last: what follows the last carriage return or newline that has text."""
    return [part for part in re.split(r"[\r\n]", stream.getvalue()) if part.strip()][-1]


def test_a_bar_that_clears_itself_on_a_terminal_ends_at_100_percent_in_a_log():
    log = io.StringIO()  # a file or a pipe: no terminal
    for _ in progress_bar(range(3), desc="random/test_seen", leave=False, file=log, mininterval=3600):
        pass  # no redraw between the first and the last item (tqdm redraws at most every `mininterval` s)
    assert "100%" in _last_draw(log) and "3/3" in _last_draw(log), log.getvalue()

    terminal = Terminal()
    for _ in progress_bar(range(3), leave=False, file=terminal, mininterval=3600):
        pass
    assert "3/3" not in terminal.getvalue()  # cleared on close, as asked


def test_the_package_draws_its_bars_through_utils_progress():
    users = sorted(
        str(path.relative_to(PACKAGE))
        for path in PACKAGE.rglob("*.py")
        if re.search(r"^\s*(from tqdm|import tqdm)", path.read_text(), re.MULTILINE)
    )
    assert users == ["utils/progress.py"]

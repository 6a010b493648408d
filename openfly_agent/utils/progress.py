"""The package's progress bars: tqdm, whose last state reaches a log file too.

tqdm redraws at most every `mininterval` (0.1 s) and a bar made with `leave=False` erases itself on close
instead of drawing its final state. On a terminal that is what one wants; written to a file or a pipe (a job's
log), the erasing is only a carriage return, so the log kept the last redraw before the end ("95%", "1/3").
Here a bar that would clear itself does so on a terminal only; elsewhere it is kept and closes at 100 %.
"""

from __future__ import annotations

import sys
from typing import Any

from tqdm.auto import tqdm


def progress_bar(iterable: Any = None, *, leave: bool = True, **kwargs: Any) -> tqdm:
    """`tqdm(iterable, leave=..., **kwargs)`, with `leave=False` honoured only when the bar's stream (`file`,
    stderr by default) is a terminal."""
    stream = kwargs.get("file") or sys.stderr
    interactive = bool(getattr(stream, "isatty", lambda: False)())
    return tqdm(iterable, leave=leave or not interactive, **kwargs)

"""Progress of the frame loop on stderr: a live bar on a terminal, sparse lines in a log.

A tqdm bar redraws itself with carriage returns several times a second; written to a file or a
pipe (``mslam run ... 2> run.log``, CI logs) that is hundreds of unreadable partial lines. So
when the stream is not a terminal the loop prints at most :data:`LOG_LINES` whole lines instead
(``frame 30/150 (20%), 6.1 s, kf=4 mode=TRACKING last=tracked``).

Public names, in reading order:
    LOG_LINES, progress_bar, LineProgress
"""

from __future__ import annotations

import math
import sys
import time
from typing import Any, TextIO

__all__ = ["LOG_LINES", "LineProgress", "progress_bar"]

#: Progress lines per run when stderr is not a terminal (one every ~10 % of the frames).
LOG_LINES = 10


def progress_bar(total: int, stream: TextIO | None = None) -> Any:
    """A tqdm bar when ``stream`` (default ``sys.stderr``) is a terminal, else a :class:`LineProgress`.

    Both have ``update(n)``, ``set_postfix(refresh=False, **fields)`` and ``close()``.
    """
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    if callable(isatty) and isatty():
        from tqdm import tqdm

        return tqdm(total=total, file=stream, unit="frame", dynamic_ncols=True, leave=False)
    return LineProgress(total, stream)


class LineProgress:
    """Whole progress lines, one each ``ceil(total / lines)`` frames and one at the end."""

    def __init__(self, total: int, stream: TextIO, lines: int = LOG_LINES) -> None:
        self.total, self.stream = int(total), stream
        self.every = max(1, math.ceil(self.total / max(1, lines)))
        self.n = 0
        self.postfix: dict[str, Any] = {}
        self.t0 = time.perf_counter()

    def set_postfix(self, refresh: bool = False, **fields: Any) -> None:
        """Remember the fields shown on the next line (``refresh`` is accepted and ignored)."""
        self.postfix = fields

    def update(self, n: int = 1) -> None:
        """Advance by ``n`` frames; print a line at each step of ``every`` frames and at the end."""
        before, self.n = self.n, self.n + n
        if self.n // self.every > before // self.every or (self.n >= self.total > before):
            self._line()

    def close(self) -> None:
        """Nothing to clear: every line is already complete."""

    def _line(self) -> None:
        pct = f" ({100 * self.n / self.total:.0f}%)" if self.total else ""
        extra = " ".join(f"{k}={v}" for k, v in self.postfix.items())
        seconds = time.perf_counter() - self.t0
        text = f"frame {self.n}/{self.total}{pct}, {seconds:.1f} s{', ' + extra if extra else ''}"
        print(text, file=self.stream, flush=True)

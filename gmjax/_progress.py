"""The one progress display of gmjax (Monte Carlo studies, tuning, the Monte Carlo PCRB).

One line on stderr, redrawn in place with a carriage return: a bar, ``done/total unit``, the rate
and the ETA. A carriage return redraws the line in a terminal and in a Jupyter notebook's stream
output alike; when stderr is neither (a log file), only every tenth of the way and the end are
written, each on its own line. :meth:`Progress.compiling` announces a compilation and its elapsed
time. ``enabled=False`` prints nothing.
"""

from __future__ import annotations

import contextlib
import sys
import time
from typing import IO, Iterator

__all__ = ["Progress"]


def _in_jupyter() -> bool:
    """True inside a running Jupyter kernel (not merely when ipykernel has been imported)."""
    ipython = sys.modules.get("IPython")
    get = getattr(ipython, "get_ipython", None)
    shell = get() if callable(get) else None
    return type(shell).__name__ == "ZMQInteractiveShell"


def _interactive(stream: IO[str]) -> bool:
    if _in_jupyter():
        return True
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


def _fmt_seconds(s: float) -> str:
    if s != s or s == float("inf"):
        return "?"
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m:02d}:{sec:02d}"


class Progress:
    """A progress line over ``total`` items.

    Args:
        total: number of items (runs, steps, chunks).
        desc: label printed first.
        unit: item name (``"runs"``).
        enabled: ``False`` prints nothing.
        stream: where to write (default ``sys.stderr``).
        min_interval_s: at most one redraw per this many seconds (the last one always shows).
    """

    def __init__(
        self,
        total: int,
        desc: str = "",
        unit: str = "runs",
        *,
        enabled: bool = True,
        stream: IO[str] | None = None,
        min_interval_s: float = 0.1,
        initial: int = 0,
    ):
        self.total = max(int(total), 1)
        self.desc = desc
        self.unit = unit
        self.enabled = enabled
        self.stream = sys.stderr if stream is None else stream
        self.min_interval_s = min_interval_s
        self.initial = self.done = int(initial)
        self.started = time.perf_counter()
        self._last_draw = -float("inf")
        self._last_decile = -1
        self._interactive = _interactive(self.stream) if enabled else False

    def write(self, message: str) -> None:
        """Print a line (e.g. a per-step report) without disturbing the bar."""
        if self.enabled:
            self.stream.write(message + "\n")
            self.stream.flush()

    @contextlib.contextmanager
    def compiling(self, what: str = "") -> Iterator[None]:
        """Context manager: ``compiling ... done in X s`` around a compilation."""
        t0 = time.perf_counter()
        label = f"{self.desc}: " if self.desc else ""
        if self.enabled:
            self.stream.write(f"{label}compiling{' ' + what if what else ''} ...")
            self.stream.flush()
        try:
            yield
        except BaseException:
            if self.enabled:  # end the line, so the error starts on its own
                self.stream.write(" failed\n")
                self.stream.flush()
            raise
        if self.enabled:
            self.stream.write(f" done in {time.perf_counter() - t0:.1f} s\n")
            self.stream.flush()
        self.started = time.perf_counter()  # rates exclude compilation

    def update(self, n: int = 1, *, postfix: str = "") -> None:
        """Advance by ``n`` items and redraw."""
        self.done = min(self.done + int(n), self.total)
        self._draw(postfix)

    def _draw(self, postfix: str = "") -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        final = self.done >= self.total
        if self._interactive:
            if not final and now - self._last_draw < self.min_interval_s:
                return
        else:
            decile = int(10 * self.done / self.total)
            if not final and decile == self._last_decile:
                return
            self._last_decile = decile
        self._last_draw = now
        elapsed = now - self.started
        new = self.done - self.initial
        rate = new / elapsed if elapsed > 0 and new > 0 else float("nan")
        eta = (self.total - self.done) / rate if rate == rate and rate > 0 else float("nan")
        width = 30
        filled = int(width * self.done / self.total)
        bar = "#" * filled + "." * (width - filled)
        label = f"{self.desc} " if self.desc else ""
        rate_s = f"{rate:.1f}" if rate == rate else "?"
        line = (
            f"{label}[{bar}] {self.done}/{self.total} {self.unit}  {rate_s} {self.unit}/s  "
            f"elapsed {_fmt_seconds(elapsed)}  ETA {_fmt_seconds(eta if not final else 0.0)}"
            f"{'  ' + postfix if postfix else ''}"
        )
        if self._interactive:
            self.stream.write("\r" + line + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

"""A progress line for long runs: steps/s and the last CG report, without stalling the GPU.

The solver's report holds device tensors; reading one (``.item()``) waits for the GPU. The line
is therefore refreshed at most every ``interval`` seconds of wall time, and only then does it read
the report: between refreshes, steps are queued back to back.
"""
from __future__ import annotations

import sys
import time
from typing import Optional, TextIO


class ProgressLine:
    """``step 40/100 [#####.....]  t 0.400 s  25.3 steps/s  CG 31 it, rel. residual 8.1e-05``.

    On a terminal the line is redrawn in place (carriage return); elsewhere (a log file, a pipe)
    each refresh is a new line.

    Args:
        total: steps the run will take.
        stream: where to write (default ``sys.stderr``).
        interval: minimum seconds between refreshes.
        clock: a ``time.perf_counter``-like function (tests pass a fake one).
    """

    def __init__(self, total: int, stream: Optional[TextIO] = None, interval: float = 0.5,
                 clock=time.perf_counter):
        self.total = int(total)
        self.stream = stream if stream is not None else sys.stderr
        self.interval = float(interval)
        self.clock = clock
        self.start = clock()
        self.last_refresh = self.start
        self.refreshes = 0  # how many times the report was read (each one a device sync)
        self.in_place = bool(getattr(self.stream, "isatty", lambda: False)())
        self._width = 0

    def update(self, done: int, simulator) -> None:
        """Note that ``done`` steps are finished; redraw if ``interval`` has passed."""
        now = self.clock()
        if now - self.last_refresh >= self.interval:
            self.last_refresh = now
            self._draw(done, simulator, now)

    def finish(self, done: int, simulator) -> None:
        """Draw the final state and end the line."""
        self._draw(done, simulator, self.clock())
        if self.in_place:
            self.stream.write("\n")
            self.stream.flush()

    def _draw(self, done: int, simulator, now: float) -> None:
        self.refreshes += 1
        elapsed = max(now - self.start, 1e-12)
        bar_len = 20
        filled = bar_len * done // max(self.total, 1)
        text = (f"step {done}/{self.total} [{'#' * filled}{'.' * (bar_len - filled)}]  "
                f"t {simulator.time:.3f} s  {done / elapsed:.1f} steps/s")
        report = simulator.last_report
        if report is not None and report.cg:
            cg = report.cg[-1]  # the last Newton iteration of the last step, worst object
            text += (f"  CG {int(cg.iterations.max())} it, "
                     f"rel. residual {float(cg.relative_residual.max()):.1e}")
        if self.in_place:
            pad = max(self._width - len(text), 0)
            self._width = len(text)
            self.stream.write("\r" + text + " " * pad)
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

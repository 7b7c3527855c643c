"""Progress of a run (a tqdm bar): steps, simulated time, steps/s of the simulation alone and the
last CG report, without stalling the GPU.

The solver's report holds device tensors; reading one (``.item()``) waits for the GPU. The
report is therefore read at most every ``interval`` seconds of wall time: between reads, steps
are queued back to back. The steps/s shown count only the time spent stepping (the caller says
how much), not the time spent writing or rendering frames.
"""
from __future__ import annotations

import sys
import time
from typing import Optional, TextIO

from tqdm import tqdm


class Progress:
    """``cantilever: 40%|####      | 40/100 [00:01<00:02, t=0.400 s, 25.3 steps/s, CG 31 it, res 8.1e-05]``.

    Args:
        total: steps the run will take.
        stream: where to write (default ``sys.stderr``).
        interval: minimum seconds between two reads of the solver's report.
        clock: a ``time.perf_counter``-like function (tests pass a fake one).
        label: the bar's prefix (the scene's name).
    """

    def __init__(self, total: int, stream: Optional[TextIO] = None, interval: float = 0.5,
                 clock=time.perf_counter, label: str = ""):
        self.total = int(total)
        self.interval = float(interval)
        self.clock = clock
        self.last_read = clock()
        self.reads = 0  # how many times the report was read (each one a device sync)
        self.postfix = ""
        self.bar = tqdm(total=self.total, desc=label or None, unit="step", file=stream or sys.stderr,
                        mininterval=self.interval, dynamic_ncols=True, leave=True,
                        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}{postfix}]")

    def update(self, done: int, simulator, stepping_seconds: float) -> None:
        """``done`` steps are finished, ``stepping_seconds`` of wall time spent in them; the
        postfix (which reads the report) is refreshed once ``interval`` has passed."""
        now = self.clock()
        if now - self.last_read >= self.interval:
            self.last_read = now
            self._read(done, simulator, stepping_seconds)
        self.bar.update(done - self.bar.n)

    def finish(self, done: int, simulator, stepping_seconds: float) -> None:
        """Show the final state and close the bar."""
        self._read(done, simulator, stepping_seconds)
        self.bar.update(done - self.bar.n)
        self.bar.close()

    def _read(self, done: int, simulator, stepping_seconds: float) -> None:
        self.reads += 1
        text = f"t={simulator.time:.3f} s, {done / max(stepping_seconds, 1e-12):.1f} steps/s"
        report = simulator.last_report
        if report is not None and report.cg:
            cg = report.cg[-1]  # the last Newton iteration of the last step, worst object
            text += f", CG {int(cg.iterations.max())} it, res {float(cg.relative_residual.max()):.1e}"
        self.postfix = text
        self.bar.set_postfix_str(text, refresh=False)

"""A scalpel: a straight blade edge moving along a path, cutting a body as it goes.

The path is keyframes of the edge (its two end points) over time, linear in between. Before each
step from t to t + dt, the simulator cuts the body where it is then along the surface the edge
sweeps from t - dt to t + dt (``Scalpel.blade``, a ``mesh.cutting.Blade`` of two triangles): the
strips of consecutive steps overlap by one step, so that a face the body carries across the
boundary between two strips is still cut (a face cut twice is cut once: after its nodes split it
joins nothing; until then it is kept parted, ``cutting.cut``'s slit). Over a run the body is cut
along the whole swept surface, a strip at a time. A body that moves across the blade faster than
the blade moves along it can still slip a face between strips and keep a bridge: cut with a
slower scalpel, or a smaller dt. Outside the keyframes' times the scalpel cuts nothing.

    scalpel = tm.Scalpel("block", times=[0.1, 0.6], edges=[[[0.3, -1, 0], [0.3, -1, 1]],
                                                            [[0.3, 1, 0], [0.3, 1, 1]]])
    sim.add_scalpel(scalpel)       # sim.step() cuts before each step
"""
from __future__ import annotations

import bisect
from typing import Optional, Sequence, Union

import numpy as np
import torch

from ..errors import SceneError
from ..mesh.cutting import Blade


class Scalpel:
    """A blade edge cutting one body along a path.

    Args:
        body: the body cut: its index or name in the simulator.
        times: keyframe times ``[K]``, K >= 2, strictly increasing (s).
        edges: the edge's two end points at each keyframe ``[K, 2, 3]``.

    Raises:
        SceneError: times not increasing, shapes that do not match, non-finite values.
    """

    def __init__(self, body: Union[int, str], times: Sequence[float], edges):
        if isinstance(body, bool) or not isinstance(body, (int, str)):
            raise SceneError(f"a scalpel's body must be a body index or name, got {body!r}")
        times = torch.as_tensor(times, dtype=torch.float64)
        edges = torch.as_tensor(edges, dtype=torch.float64)
        if times.dim() != 1 or times.numel() < 2:
            raise SceneError(f"a scalpel's times must be a list of at least 2 keyframe times, got shape "
                             f"{tuple(times.shape)}")
        if edges.shape != (times.numel(), 2, 3):
            raise SceneError(f"a scalpel's edges must be [K, 2, 3] (two end points per keyframe, K = "
                             f"{times.numel()}), got shape {tuple(edges.shape)}")
        if not bool(torch.isfinite(times).all() and torch.isfinite(edges).all()):
            raise SceneError("a scalpel's times and edges must be finite")
        if not bool((times[1:] > times[:-1]).all()):
            raise SceneError(f"a scalpel's times must increase strictly, got {times.tolist()}")
        self.body = body
        self.times = times
        self.edges = edges

    def _keyframes(self):
        """The keyframes as a list of times and an ``[K, 2, 3]`` numpy array (made once: a scalpel is
        read before every step, and a few numpy operations on the host cost less than torch's)."""
        keyframes = self.__dict__.get("_keyframes_on_host")
        if keyframes is None:
            keyframes = self.__dict__["_keyframes_on_host"] = (self.times.tolist(), self.edges.numpy().copy())
        return keyframes

    def _edge(self, t: float) -> np.ndarray:
        times, edges = self._keyframes()
        t = min(max(float(t), times[0]), times[-1])
        k = min(bisect.bisect_right(times, t) - 1, len(times) - 2)
        s = (t - times[k]) / (times[k + 1] - times[k])
        return (1 - s) * edges[k] + s * edges[k + 1]

    def edge(self, t: float) -> torch.Tensor:
        """The edge's end points at time t ``[2, 3]`` (float64), clamped to the first and last keyframes."""
        return torch.from_numpy(self._edge(t))

    def strip(self, t0: float, t1: float) -> Optional[torch.Tensor]:
        """The corners ``[4, 3]`` (float64) of the surface the edge sweeps from time t0 to t1 (within
        the keyframes' times), in :meth:`Blade.swept`'s order (the edge at the start, then at the
        end reversed), or None where it sweeps nothing (outside them, or the edge stands still)."""
        times, _ = self._keyframes()
        start, end = max(float(t0), times[0]), min(float(t1), times[-1])
        if end <= start:
            return None
        a, b = self._edge(start), self._edge(end)
        if np.array_equal(a, b):
            return None
        return torch.from_numpy(np.stack([a[0], a[1], b[1], b[0]]))

    def blade(self, t0: float, t1: float) -> Optional[Blade]:
        """The surface the edge sweeps from time t0 to t1 (:meth:`strip`) as a ``Blade`` (two
        triangles), or None where it sweeps nothing."""
        corners = self.strip(t0, t1)
        return None if corners is None else Blade.strip(corners)

    def __repr__(self) -> str:
        return (f"Scalpel(body={self.body!r}, times=[{float(self.times[0]):g} .. {float(self.times[-1]):g}], "
                f"{self.times.numel()} keyframes)")

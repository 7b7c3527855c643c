"""Writing simulation frames: one .vtu per body and frame, and a .pvd time series for ParaView."""
from __future__ import annotations

import os
from pathlib import Path
from typing import List, Tuple
from xml.sax.saxutils import quoteattr

from .io import save_mesh


class FrameWriter:
    """Writes ``<out>/<name>_<body>_<frame>.vtu`` files and ``<out>/<name>.pvd`` indexing them.

    Each frame holds the deformed mesh with point data ``displacement`` and ``velocity`` ``[V, 3]``.
    """

    def __init__(self, out_dir, name: str):
        self.out_dir = Path(out_dir)
        self.name = name
        self.entries: List[Tuple[float, int, str]] = []
        self.frame = 0

    def write(self, simulator) -> None:
        """Write the current state of every body of ``simulator``."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for i, body in enumerate(simulator.bodies):
            mesh = type(body.mesh)(simulator.positions(i).detach(), body.mesh.elements, check=False)
            file = f"{self.name}_{i}_{self.frame:05d}.vtu"
            save_mesh(self.out_dir / file, mesh, displacement=simulator.displacements(i).detach(),
                      velocity=simulator.velocities(i).detach())
            self.entries.append((simulator.time, i, file))
        self.frame += 1
        self._write_pvd()

    def _write_pvd(self) -> None:
        lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">', "  <Collection>"]
        for time, part, file in self.entries:
            lines.append(f'    <DataSet timestep="{time:.9g}" part="{part}" file={quoteattr(file)}/>')
        lines += ["  </Collection>", "</VTKFile>", ""]
        # written beside, then renamed: the series always lists complete frames only
        path = self.out_dir / f"{self.name}.pvd"
        partial = path.with_name(f".{path.name}.partial")
        partial.write_text("\n".join(lines))
        os.replace(partial, path)


class FrameRenderer:
    """Off-screen pictures of the frames: ``<out>/<name>_<frame>.png`` and/or ``<out>/<name>.gif``.

    Every body of the simulator is drawn in one view. PNGs are written as frames arrive; the GIF
    is written by :meth:`close` from the positions kept for each frame (CPU copies ``[V_i, 3]``).
    ``tensormass_torch.render`` (pyvista) is imported here, so a missing pyvista fails at
    construction, before any frame is simulated or written.
    """

    def __init__(self, out_dir, name: str, *, png: bool = True, gif: bool = False,
                 window_size=(800, 600), fps: float = 10.0):
        from . import render

        render._pyvista()  # fail now (ImportError with an install hint), not after the run
        self._render = render
        self.out_dir = Path(out_dir)
        self.name = name
        self.png, self.gif = png, gif
        self.window_size = tuple(window_size)
        self.fps = fps
        self.frame = 0
        self.frames: List[list] = []
        self.files: List[Path] = []

    def _panels(self, simulator) -> list:
        return [[(body.mesh, simulator.positions(i).detach().cpu())
                 for i, body in enumerate(simulator.bodies)]]

    def write(self, simulator) -> None:
        """Draw the current state of every body of ``simulator``."""
        panels = self._panels(simulator)
        if self.png:
            file = self.out_dir / f"{self.name}_{self.frame:05d}.png"
            self.files.append(self._render.render_png(file, panels, window_size=self.window_size))
        if self.gif:
            self.frames.append(panels)
        self.frame += 1

    def close(self) -> None:
        """Write the GIF of every frame drawn so far (if asked for)."""
        if self.gif and self.frames:
            file = self.out_dir / f"{self.name}.gif"
            self.files.append(self._render.render_gif(file, self.frames, fps=self.fps,
                                                       window_size=self.window_size))
            self.frames = []

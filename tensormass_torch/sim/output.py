"""Writing simulation frames: one .vtu per body and frame, and a .pvd time series for ParaView
(pictures of the frames: ``app.render.FrameRenderer``)."""
from __future__ import annotations

import os
from pathlib import Path
from typing import List, Tuple
from xml.sax.saxutils import quoteattr

from ..mesh.io import save_mesh


class FrameWriter:
    """Writes ``<out>/<name>_<body>_<frame>.vtu`` files and ``<out>/<name>.pvd`` indexing them.

    Each frame holds the deformed mesh with point data ``displacement`` and ``velocity`` ``[V, 3]``.
    ``series=False``: no ``.pvd`` (a process of a batch over several writes its bodies' files; one
    of them writes the series of all, :meth:`write_series`).
    """

    def __init__(self, out_dir, name: str, series: bool = True):
        self.out_dir = Path(out_dir)
        self.name = name
        self.series = series
        self.entries: List[Tuple[float, int, str]] = []
        self.frame = 0

    def write(self, simulator, body_ids=None) -> List[Tuple[float, int, str]]:
        """Write the current state of every body of ``simulator`` (``body_ids``: the number each
        body goes by in the file names and the series, default its index); returns this frame's
        entries ``(time, body, file)``."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for i, body in enumerate(simulator.bodies):
            part = i if body_ids is None else int(body_ids[i])
            # the mesh as it is now: removed elements left out, split nodes apart (simulator.mesh)
            mesh = type(body.mesh)(simulator.positions(i).detach(), simulator.mesh(i).elements, check=False)
            file = f"{self.name}_{part}_{self.frame:05d}.vtu"
            save_mesh(self.out_dir / file, mesh, displacement=simulator.displacements(i).detach(),
                      velocity=simulator.velocities(i).detach())
            written.append((simulator.time, part, file))
        self.entries += written
        self.frame += 1
        if self.series:
            self._write_pvd()
        return written

    def write_series(self, entries) -> None:
        """Write ``<name>.pvd`` indexing ``entries`` ``[(time, body, file)]`` (the files of every
        process of a batch), sorted by time and body."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self._write_pvd(sorted(entries))

    def _write_pvd(self, entries=None) -> None:
        lines = ['<?xml version="1.0"?>', '<VTKFile type="Collection" version="0.1">', "  <Collection>"]
        for time, part, file in (self.entries if entries is None else entries):
            lines.append(f'    <DataSet timestep="{time:.9g}" part="{part}" file={quoteattr(file)}/>')
        lines += ["  </Collection>", "</VTKFile>", ""]
        # written beside, then renamed: the series always lists complete frames only
        path = self.out_dir / f"{self.name}.pvd"
        partial = path.with_name(f".{path.name}.partial")
        partial.write_text("\n".join(lines))
        os.replace(partial, path)

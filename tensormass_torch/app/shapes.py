"""Triangle surfaces of the rigid tools, to draw them: the off-screen pictures (``app.render``)
and the live viewer (``app.viewer``) take them from here, so that a tool looks the same in both.

    tool_surface(tool) -> (vertices [K, 3], triangles [F, 3])
        numpy, float64 / int64: the tool's shape turned by its rotation, about its origin (add
        the origin at a time: ``ToolSet.origin_at``); closed and wound outward

A sphere and a capsule are drawn as polyhedra inscribed in them (their vertices on the surface),
a box exactly, a mesh tool (``tm.MeshTool``) as the surface it was built from (its contact is
that surface's signed distance sampled on a grid: corners rounded over about a cell).
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

from ..errors import SceneError

#: The colour tools are drawn in (the viewer's RGB, the pictures' hex of it).
TOOL_RGB = (214, 95, 95)
TOOL_COLOR = "#d65f5f"
#: Rings and segments of the polyhedra drawn for spheres and capsules.
RINGS, SEGMENTS = 16, 32


def _sphere(radius: float, rings: int, segments: int, stretch: float = 0.0):
    """A UV sphere of ``radius`` about the origin, its poles on the x axis; with ``stretch`` > 0
    the half at x >= 0 moved by +stretch along x and the other by -stretch (a capsule: the band
    between the two middle rings becomes its cylinder). ``rings`` even, so that a ring lies at x = 0."""
    polar = np.pi * np.arange(1, rings) / rings  # the rings between the poles
    around = 2 * np.pi * np.arange(segments) / segments
    x = np.cos(polar)[:, None].repeat(segments, 1)
    y = np.sin(polar)[:, None] * np.cos(around)[None, :]
    z = np.sin(polar)[:, None] * np.sin(around)[None, :]
    ring_points = radius * np.stack([x, y, z], -1).reshape(-1, 3)
    points = np.concatenate([[[radius, 0.0, 0.0]], ring_points, [[-radius, 0.0, 0.0]]])
    if stretch > 0:
        points[:, 0] += np.where(np.arange(points.shape[0]) <= (rings // 2) * segments, stretch, -stretch)
    last = points.shape[0] - 1
    ring = lambda r, s: 1 + r * segments + s % segments  # noqa: E731
    faces = []
    for s in range(segments):  # the caps, then the bands between rings
        faces.append((0, ring(0, s), ring(0, s + 1)))
        faces.append((last, ring(rings - 2, s + 1), ring(rings - 2, s)))
        for r in range(rings - 2):
            faces.append((ring(r, s), ring(r + 1, s + 1), ring(r, s + 1)))
            faces.append((ring(r, s), ring(r + 1, s), ring(r + 1, s + 1)))
    return points, np.asarray(faces, dtype=np.int64)


def _box(half_extents) -> Tuple[np.ndarray, np.ndarray]:
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    points = corners * np.asarray(half_extents, dtype=np.float64)
    # two triangles a face, wound outward (corner index = 4 [x > 0] + 2 [y > 0] + [z > 0])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
    return points, np.asarray(faces, dtype=np.int64)


def tool_surface(tool) -> Tuple[np.ndarray, np.ndarray]:
    """The surface of ``tool`` (a ``tm.Tool``) in world axes about its origin: ``(vertices [K, 3]
    float64, triangles [F, 3] int64)``, closed and wound outward. Raises SceneError for a shape
    it does not know (or a mesh tool made without ``tm.MeshTool``, which keeps no surface)."""
    if tool.shape == "sphere":
        points, faces = _sphere(tool.size[0], RINGS, SEGMENTS)
    elif tool.shape == "capsule":  # its segment along the tool's first axis
        points, faces = _sphere(tool.size[0], RINGS, SEGMENTS, stretch=tool.size[1])
    elif tool.shape == "box":
        points, faces = _box(tool.size)
    elif tool.shape == "mesh" and tool.surface is not None:
        points, faces = (np.asarray(t.numpy(), dtype=dtype) for t, dtype in zip(tool.surface, (np.float64, np.int64)))
    else:
        raise SceneError(f"cannot draw a tool of shape {tool.shape!r}"
                         + (" without its surface (build it with tm.MeshTool)" if tool.shape == "mesh" else ""))
    rotation = np.asarray(tool.rotation, dtype=np.float64)  # the tool's axes as columns
    return points @ rotation.T, faces

"""The tools' surfaces that pictures and the viewer draw (``app.shapes.tool_surface``): closed,
wound outward, on the shape's surface (vertices of the inscribed polyhedra at the radius, a box's
corners), turned by the tool's rotation; a mesh tool's own triangles; a shape it cannot draw is
one error."""
from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.app.shapes import tool_surface
from tensormass_torch.errors import SceneError


def closed_and_outward(vertices, faces):
    """Every directed edge once, its reverse once (closed, consistently wound); the signed
    volume (positive where wound outward)."""
    directed = Counter((int(t[i]), int(t[(i + 1) % 3])) for t in faces for i in range(3))
    assert all(count == 1 for count in directed.values())
    assert all((b, a) in directed for a, b in directed)
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6)


def turn(angle):
    c, s = np.cos(angle), np.sin(angle)
    return [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]


def test_a_sphere_is_a_closed_polyhedron_on_its_radius():
    vertices, faces = tool_surface(tm.Sphere(0.3, position=(5.0, 0.0, 0.0)))
    assert np.allclose(np.linalg.norm(vertices, axis=1), 0.3)  # about the origin: the position is added later
    volume = closed_and_outward(vertices, faces)
    assert 0.95 * (4 / 3) * np.pi * 0.3 ** 3 < volume < (4 / 3) * np.pi * 0.3 ** 3


def test_a_capsule_lies_on_its_radius_around_its_segment_along_the_first_axis():
    rotation = turn(0.7)
    vertices, faces = tool_surface(tm.Capsule(0.1, 0.25, rotation=rotation))
    axis = np.asarray(rotation)[:, 0]
    along = np.clip(vertices @ axis, -0.25, 0.25)
    assert np.allclose(np.linalg.norm(vertices - along[:, None] * axis, axis=1), 0.1)
    assert np.isclose((vertices @ axis).max(), 0.35)
    exact = (4 / 3) * np.pi * 0.1 ** 3 + np.pi * 0.1 ** 2 * 0.5
    assert 0.95 * exact < closed_and_outward(vertices, faces) < exact


def test_a_box_is_its_eight_corners_turned():
    rotation = turn(0.3)
    vertices, faces = tool_surface(tm.Box((0.1, 0.2, 0.3), rotation=rotation))
    local = vertices @ np.asarray(rotation)  # back in the box's axes
    assert np.allclose(np.abs(local), [0.1, 0.2, 0.3])
    assert len({tuple(np.sign(p)) for p in local}) == 8
    assert np.isclose(closed_and_outward(vertices, faces), 8 * 0.1 * 0.2 * 0.3)


def test_a_mesh_tool_is_drawn_as_its_own_surface():
    cube = tm.beam_mesh(1, 1, 1, size=(0.2, 0.2, 0.2), dtype=torch.float64)
    from tensormass_torch.mesh.topology import boundary_faces

    triangles = boundary_faces(cube.elements)
    tool = tm.MeshTool((cube.vertices, triangles), rotation=turn(0.5), resolution=8)
    vertices, faces = tool_surface(tool)
    assert np.array_equal(faces, triangles.numpy())
    assert np.allclose(vertices, cube.vertices.numpy() @ np.asarray(turn(0.5)).T)
    assert np.isclose(closed_and_outward(vertices, faces), 0.2 ** 3)


def test_a_shape_it_cannot_draw_is_one_error():
    # stand-ins: tm.Tool itself refuses an unknown shape, and tm.MeshTool always keeps the surface
    for tool, message in ((SimpleNamespace(shape="cone", size=(), surface=None), "cannot draw a tool of shape 'cone'"),
                          (SimpleNamespace(shape="mesh", size=(), surface=None), "without its surface")):
        with pytest.raises(SceneError, match=message):
            tool_surface(tool)

"""Meshes of implicit shapes: close to the exact volume, positively oriented, connected, no unused
vertex, boundary on the surface; the rabbit-like body is one valid piece."""
import math

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.mesh import implicit as meshgen
from tensormass_torch.mesh.implicit import _boundary_nodes, _largest_component


def check_clean(mesh, cell):
    """Valid, positive, no unused vertex, face-connected; returns the boundary node mask [V]."""
    tm.TetMesh(mesh.vertices, mesh.elements)  # validates again from scratch
    volumes = mesh.signed_measures()
    assert float(volumes.min()) >= 0.25 * cell ** 3 / 6 * (1 - 1e-9)  # the snap's volume floor
    assert mesh.unused_vertices().numel() == 0
    tets = mesh.elements.numpy()
    assert _largest_component(tets).all()
    return torch.from_numpy(_boundary_nodes(tets, mesh.num_vertices))


def test_sphere_volume_converges_and_boundary_is_on_the_surface():
    radius, exact = 1.0, 4.0 / 3.0 * math.pi
    errors = []
    for cell in (0.25, 0.125):
        mesh = meshgen.sphere_mesh(radius, center=(0.3, -0.2, 1.0), cell=cell)
        boundary = check_clean(mesh, cell)
        errors.append(abs(float(mesh.signed_measures().sum()) / exact - 1))
        distance = (mesh.vertices[boundary] - torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)).norm(dim=1) - radius
        assert float(distance.abs().median()) < 1e-6  # snapped onto the sphere
        assert float(distance.abs().max()) < cell
    # Boundary nodes on the sphere make an inscribed polyhedron: the error falls as the cell does.
    assert errors[1] < 0.015 and errors[1] < errors[0] / 2


def test_capsule_volume():
    radius, length, cell = 0.2, 1.0, 0.05
    mesh = meshgen.capsule_mesh(radius, length, cell=cell)
    check_clean(mesh, cell)
    exact = math.pi * radius ** 2 * length + 4.0 / 3.0 * math.pi * radius ** 3
    assert abs(float(mesh.signed_measures().sum()) / exact - 1) < 0.025  # cell = radius / 4
    lo, hi = mesh.vertices.min(0).values, mesh.vertices.max(0).values
    assert torch.allclose(hi - lo, torch.tensor([length + 2 * radius, 2 * radius, 2 * radius], dtype=torch.float64),
                          atol=0.02)


def test_rabbit_is_one_clean_piece_sitting_on_its_base():
    cell = 0.08
    mesh = meshgen.rabbit_mesh(size=1.0, cell=cell, origin=(1.0, 2.0, 0.5))
    boundary = check_clean(mesh, cell)
    z = mesh.vertices[:, 2]
    assert abs(float(z.min()) - 0.5) < 1e-9  # flat base at the origin's height
    assert int((z - 0.5 < 1e-9).sum()) >= 10  # a whole face of nodes on it, not a point
    lo, hi = mesh.vertices.min(0).values, mesh.vertices.max(0).values
    extent = (hi - lo).tolist()
    assert 0.9 < extent[0] < 1.2 and 0.4 < extent[1] < 0.65 and 0.95 < extent[2] < 1.2  # long, narrow, tall (ears)
    shape = meshgen.rabbit_shape(1.0, (1.0, 2.0, 0.5))
    assert float(shape(mesh.vertices[boundary]).abs().median()) < 1e-6


def test_smooth_union_fills_the_gap():
    a = meshgen.sphere_shape(0.5, (-0.55, 0, 0))
    b = meshgen.sphere_shape(0.5, (0.55, 0, 0))
    middle = torch.zeros(1, 3, dtype=torch.float64)
    assert float(torch.minimum(a(middle), b(middle))) > 0  # a plain union leaves the gap
    assert float(meshgen.smooth_union(a, b, 0.3)(middle)) < 0


def test_bad_arguments():
    with pytest.raises(tm.MeshError, match="cell .* too large"):
        meshgen.sphere_mesh(0.1, cell=5.0)
    with pytest.raises(tm.MeshError, match="radius must be a positive"):
        meshgen.sphere_mesh(-1.0)
    with pytest.raises(tm.MeshError, match="center must be 3 finite numbers"):
        meshgen.sphere_shape(1.0, (0, 0))

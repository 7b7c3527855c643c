"""Signed distance grids of closed surfaces (mesh.distance): the grid's values against a brute-force
oracle (nearest triangle by a dense search, inside by the winding number) on a non-convex surface,
either winding; the interpolant's gradient and Hessian against autograd; the checks on open,
inconsistently wound and flat surfaces."""
import math

import numpy as np
import pytest
import torch
from conftest import u_shape_surface

import tensormass_torch as tm
from tensormass_torch.mesh import distance
from tensormass_torch.mesh.distance import (
    check_closed,
    closest_point,
    signed_distance_grid,
    signed_distances_to_surfaces,
    surface_signed_distances,
)
from tensormass_torch.mesh.topology import boundary_faces

DT = torch.float64


def winding_numbers(p, a, b, c):
    """The solid angles of the triangles seen from p over 4 pi (Van Oosterom and Strackee)."""
    ra, rb, rc = a - p[:, None], b - p[:, None], c - p[:, None]
    la, lb, lc = (r.norm(dim=-1) for r in (ra, rb, rc))
    numerator = (ra * torch.linalg.cross(rb, rc, dim=-1)).sum(-1)
    denominator = la * lb * lc + (ra * rb).sum(-1) * lc + (ra * rc).sum(-1) * lb + (rb * rc).sum(-1) * la
    return (2 * torch.atan2(numerator, denominator)).sum(-1) / (4 * math.pi)


@pytest.mark.parametrize("winding", ["outward", "inward"])
def test_grid_values_are_the_signed_distance(winding):
    vertices, faces = u_shape_surface()
    if winding == "inward":
        faces = faces[:, [0, 2, 1]]
    grid = signed_distance_grid(vertices, faces, resolution=12, margin=0.01)
    shape = grid.values.shape
    axes = [grid.lower[i] + grid.spacing * torch.arange(shape[i], dtype=DT) for i in range(3)]
    nodes = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    _, _, d, _ = closest_point(nodes[:, None], a, b, c)
    inside = winding_numbers(nodes, a, b, c).abs() > 0.5
    expected = torch.where(inside, -d.amin(1), d.amin(1))
    assert bool(inside.any()) and bool((~inside).any())
    torch.testing.assert_close(grid.values.reshape(-1), expected, rtol=0, atol=1e-12)
    # the grid reaches the margin and two cells past the surface's box
    assert float(grid.lower.max()) <= -0.01 - 2 * grid.spacing + 1e-12
    assert float(grid.values.amax()) > 0.01


def test_a_point_beside_a_crease_takes_both_faces_side_in_float32():
    # two faces of a body's surface met in a pile (float32): the point is nearest their shared
    # edge, nearly in the first face's plane; the two faces' distances differ by rounding (3e-8)
    # and the first face alone puts it inside. Both faces are nearest: outside, 1.37 mm.
    vertices = torch.tensor([[0.293292314, 0.909236073, 0.297392845], [0.292573363, 0.949234188, 0.297523677],
                             [0.332665741, 0.949838758, 0.291527212], [0.337615311, 0.949699461, 0.324701786]])
    faces = torch.tensor([[0, 1, 2], [1, 3, 2]])
    point = torch.tensor([0.293433905, 0.95062077, 0.297405183]).reshape(1, 1, 1, 3)
    signed = float(surface_signed_distances(point, vertices, faces, block=1))
    assert signed == pytest.approx(1.3735e-3, rel=1e-3)


@pytest.mark.parametrize("batch", [None, 50, 1])
def test_distances_to_several_surfaces_are_each_surfaces_own(batch, monkeypatch):
    """signed_distances_to_surfaces: each point's exact signed distance to its own surface among
    three (the U shape and two turned copies of a box's boundary, their triangles interleaved),
    the winding number's side and the dense nearest triangle's distance, in batches of whole points
    (``batch`` point-triangle pairs; 1: each point alone, past the bound)."""
    if batch is not None:
        monkeypatch.setattr(distance, "PAIRS_PER_BATCH", batch)
    gen = torch.Generator().manual_seed(5)
    u_vertices, u_faces = u_shape_surface()
    box = tm.beam_mesh(3, 2, 2, size=(0.3, 0.2, 0.25), dtype=DT)
    box_faces = boundary_faces(box.elements)
    surfaces, offset = [], 0
    for k, (verts, faces) in enumerate([(u_vertices, u_faces), (box.vertices, box_faces),
                                        (box.vertices * 0.5 + 0.1, box_faces)]):
        surfaces.append((verts, faces + offset, k))
        offset += verts.shape[0]
    vertices = torch.cat([v for v, _, _ in surfaces])
    triangles = torch.cat([f for _, f, _ in surfaces])
    triangle_surface = torch.cat([torch.full((f.shape[0],), k) for _, f, k in surfaces])
    shuffle = torch.randperm(triangles.shape[0], generator=gen)  # any order of the triangles
    points = torch.rand(60, 3, generator=gen, dtype=DT) * 0.5 - 0.1
    owner = torch.randint(0, 3, (60,), generator=gen)
    signed = signed_distances_to_surfaces(points, owner, vertices, triangles[shuffle], triangle_surface[shuffle])
    for k, (verts, faces, _) in enumerate(surfaces):
        mine = owner == k
        a, b, c = (vertices[faces[:, i]] for i in range(3))
        _, _, d, _ = closest_point(points[mine][:, None], a, b, c)
        inside = winding_numbers(points[mine], a, b, c).abs() > 0.5
        torch.testing.assert_close(signed[mine], torch.where(inside, -d.amin(1), d.amin(1)), rtol=0, atol=1e-12)
    assert bool((signed < 0).any()) and bool((signed > 0).any())
    # a point of a surface without any triangle is infinitely far
    far = signed_distances_to_surfaces(points[:2], torch.tensor([1, 3]), vertices, triangles, triangle_surface)
    near = signed_distances_to_surfaces(points[:1], torch.tensor([1]), vertices, triangles, triangle_surface)
    assert float(far[1]) == torch.finfo(DT).max and float(far[0]) == float(near[0])


def test_sample_is_the_trilinear_interpolant_and_its_derivatives():
    vertices, faces = u_shape_surface()
    grid = signed_distance_grid(vertices, faces, resolution=10)
    # at the nodes, the values
    node = torch.tensor([[3, 2, 4], [0, 0, 0], [7, 1, 5]])
    q = grid.lower + grid.spacing * node.to(DT)
    phi, _, _ = grid.sample(q)
    torch.testing.assert_close(phi, grid.values[node[:, 0], node[:, 1], node[:, 2]], rtol=0, atol=1e-12)
    # inside cells: gradient and Hessian are autograd's of phi
    gen = torch.Generator().manual_seed(2)
    cells = torch.randint(0, 8, (20, 3), generator=gen).to(DT) + 0.1 + 0.8 * torch.rand(20, 3, generator=gen,
                                                                                        dtype=DT)
    cells[:, 1] = torch.clamp(cells[:, 1], max=grid.values.shape[1] - 1.2)
    points = grid.lower + grid.spacing * cells
    phi, grad, hessian = grid.sample(points)
    for i in range(points.shape[0]):
        def f(p):
            return grid.sample(p[None])[0][0]
        torch.testing.assert_close(torch.autograd.functional.jacobian(f, points[i]), grad[i], rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(torch.autograd.functional.hessian(f, points[i]), hessian[i], rtol=1e-9,
                                   atol=1e-9)
    # beyond the grid: positive, at least the distance to its box
    far = torch.tensor([[1.0, 0.05, 0.1], [-0.5, -0.5, -0.5]], dtype=DT)
    phi, grad, _ = grid.sample(far)
    assert bool((phi > 0.3).all())
    torch.testing.assert_close(grad.norm(dim=1), torch.ones(2, dtype=DT))


def test_open_or_badly_wound_or_flat_surfaces_raise():
    vertices, faces = u_shape_surface()
    with pytest.raises(tm.MeshError, match=r"surface is not closed: 3 edges are not shared by exactly two"):
        signed_distance_grid(vertices, faces[1:])
    flipped = faces.clone()
    flipped[0] = flipped[0, [0, 2, 1]]
    with pytest.raises(tm.MeshError, match="not consistently wound"):
        check_closed(np.asarray(flipped))
    # a flat closed surface (a square's two sides) has no inside
    square = torch.tensor([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=DT)
    sides = torch.tensor([[0, 1, 2], [0, 2, 3], [1, 0, 3], [1, 3, 2]])
    with pytest.raises(tm.MeshError, match="encloses no volume"):
        signed_distance_grid(square, sides, resolution=4)
    with pytest.raises(tm.MeshError, match="resolution must be an integer"):
        signed_distance_grid(vertices, faces, resolution=0)
    with pytest.raises(tm.MeshError, match="grid spacing must be a positive"):
        signed_distance_grid(vertices, faces, spacing=-1.0)

"""Rest geometry of P1 elements: shape vectors, rest measures, tangent projectors.

For an element with rest nodes X_0..X_{n-1}, the barycentric coordinates lambda_j are linear and
their gradients m_j = grad(lambda_j) are constant. With the edge rows e_k = X_k - X_0 (k >= 1)
stacked in E ``[n-1, d]``, the m_k (k >= 1) are the rows of G = (E E^T)^{-1} E: they satisfy
m_j . e_k = delta_jk and lie in the span of the edges (the triangle's plane for a membrane in
3-D). m_0 = -sum_k m_k. For a tetrahedron E is square and G = E^{-T}.
"""
from __future__ import annotations

import torch


def element_nodes(points: torch.Tensor, elements: torch.Tensor) -> torch.Tensor:
    """Gather per-element node coordinates: points ``[V, d]``, elements ``[N, n]`` -> ``[N, n, d]``."""
    return points[elements]


def shape_vectors(rest: torch.Tensor):
    """Shape vectors and rest measures of elements.

    Args:
        rest: rest node coordinates ``[N, n, d]`` (n = 4, d = 3 for tetrahedra; n = 3, d = 2 or 3
            for triangles).

    Returns:
        m: shape vectors ``[N, n, d]``, ``sum_j m_j = 0``.
        measure: signed volume (tetrahedra), signed area (2-D triangles) or unsigned area
            (triangles in 3-D) ``[N]``.
    """
    edges = rest[:, 1:, :] - rest[:, :1, :]  # [N, n-1, d]
    n_minus_1, d = edges.shape[1], edges.shape[2]
    gram = edges @ edges.transpose(1, 2)  # [N, n-1, n-1]
    grads = torch.linalg.solve(gram, edges)  # [N, n-1, d]
    m = torch.cat([-grads.sum(dim=1, keepdim=True), grads], dim=1)
    if n_minus_1 == d:  # simplex of full dimension: signed measure
        factorial = 6.0 if d == 3 else 2.0
        measure = torch.linalg.det(edges) / factorial
    else:  # triangle in 3-D: area from the Gram determinant
        measure = 0.5 * torch.sqrt(torch.linalg.det(gram))
    return m, measure


def rest_geometry(points: torch.Tensor, elements: torch.Tensor, projectors: bool, chunk: int = 1 << 16):
    """:func:`shape_vectors` (and :func:`tangent_projectors` where ``projectors``) of the elements
    ``[N, n]`` over ``points [V, d]``: (m ``[N, n, d]``, measure ``[N]``, projectors ``[N, d, d]``
    or None), ``chunk`` elements at a time, so that the element coordinates ``[N, n, d]`` and the
    solves' temporaries (the first peak of a model's construction) are a chunk's. The same values
    to rounding (each element's are computed alone either way; a GPU's batched solves may round
    differently by batch size). At once where ``points`` requires grad."""
    count = elements.shape[0]
    if points.requires_grad or count <= chunk:
        element_rest = element_nodes(points, elements)
        m, measure = shape_vectors(element_rest)
        return m, measure, tangent_projectors(element_rest) if projectors else None
    n, d = elements.shape[1], points.shape[1]
    m, measure = points.new_empty((count, n, d)), points.new_empty((count,))
    proj = points.new_empty((count, d, d)) if projectors else None
    for start in range(0, count, chunk):
        part = slice(start, start + chunk)
        element_rest = element_nodes(points, elements[part])
        m[part], measure[part] = shape_vectors(element_rest)
        if projectors:
            proj[part] = tangent_projectors(element_rest)
    return m, measure, proj


def tangent_projectors(rest: torch.Tensor) -> torch.Tensor:
    """Orthogonal projectors onto the rest plane of triangles in 3-D: ``[N, 3, 3]``.

    P = E^T (E E^T)^{-1} E, i.e. I - n n^T with n the unit normal. Membrane strains are taken
    in this plane only.
    """
    edges = rest[:, 1:, :] - rest[:, :1, :]
    gram = edges @ edges.transpose(1, 2)
    return edges.transpose(1, 2) @ torch.linalg.solve(gram, edges)


def needs_projector(nodes_per_element: int, dim: int) -> bool:
    """Whether elements of this kind live in a space larger than themselves (membranes in 3-D)."""
    return nodes_per_element - 1 < dim

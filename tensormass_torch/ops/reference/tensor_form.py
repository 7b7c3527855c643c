"""Tensor form: forces from precomputed Tensor-Mass tensors.

``hooke`` (Cotin, Delingette, Ayache 2000): per element
    K_jk = vol (lam m_j m_k^T + mu m_k m_j^T + mu (m_j . m_k) P)          [N, n, n, d, d]
summed over the elements that share them into Cotin's vertex tensors K_ii and edge tensors K_ij
``[Ed, d, d]`` (i < j; K_ji = K_ij^T): F_i = -K_ii u_i - sum_j K_ij u_j. Every row of an element's
blocks sums to zero (sum_k m_k = 0), so K_ii = -sum_j K_ij exactly and F_i = -sum_j K_ij (u_j - u_i):
only the edge tensors are assembled, and the differences keep float32's digits (the absolute form
cancels large displacements against each other: 0.3-0.6 % errors in float32).

``stvk`` (Picinbono, Delingette, Ayache): per element
    W = sum_jk u_j^T B_jk u_k + sum_jkl (u_j.u_k)(C_jkl.u_l) + sum_jklm D_jklm (u_j.u_k)(u_l.u_m)
    B_jk   = K_jk / 2                                                      [N, n, n, d, d]
    C_jkl  = vol (lam/2 (m_j.m_k) m_l + mu/2 ((m_l.m_j) m_k + (m_l.m_k) m_j))   [N, n, n, n, d]
    D_jklm = vol (lam/8 (m_j.m_k)(m_l.m_m) + mu/8 ((m_j.m_m)(m_k.m_l) + (m_j.m_l)(m_k.m_m)))
                                                                          [N, n, n, n, n]
D is stored symmetrised over j<->k, l<->m and (jk)<->(lm) (it multiplies a product symmetric
in those), which gives the compact force -dW/du_p below. P is the membrane's tangent projector
(identity for tetrahedra and 2-D triangles); C and D need none since the m_j lie in the plane.
"""
from __future__ import annotations

import torch

from ...mesh.topology import incidence_slots, padded_sum, unique_edges


def _plane_identity(m: torch.Tensor, proj):
    d = m.shape[-1]
    if proj is None:
        return torch.eye(d, dtype=m.dtype, device=m.device).expand(m.shape[0], d, d)
    return proj


def stiffness_blocks(m_j, m_k, vol, lam, mu, plane) -> torch.Tensor:
    """Cotin's blocks K_jk = vol (lam m_j m_k^T + mu m_k m_j^T + mu (m_j . m_k) P) of shape vectors
    ``m_j, m_k [N, ..., d]`` (broadcast against each other), with ``vol, lam, mu [N]`` and the
    projector ``plane [N, d, d]``: ``[N, ..., d, d]``. The one place the formula is written."""
    inner = max(m_j.dim(), m_k.dim()) - 2  # the dims between N and d

    def per_element(t, trailing=0):
        return t.reshape(t.shape[0], *([1] * (inner + trailing)))

    k = per_element(lam, 2) * (m_j[..., :, None] * m_k[..., None, :])
    k = k + per_element(mu, 2) * (m_k[..., :, None] * m_j[..., None, :])
    k = k + (per_element(mu) * (m_j * m_k).sum(-1))[..., None, None] * plane.reshape(
        plane.shape[0], *([1] * inner), *plane.shape[1:])
    return per_element(vol, 2) * k


def element_stiffness(m, vol, lam, mu, proj=None) -> torch.Tensor:
    """Cotin's element tensors K_jk ``[N, n, n, d, d]``."""
    return stiffness_blocks(m[:, :, None], m[:, None], vol, lam, mu, _plane_identity(m, proj))


def oriented_blocks(element_k: torch.Tensor, elements: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """The element tensors of each local pair (a < b) ``[N, P, d, d]`` as their edge stores them:
    from the lower to the higher global node (K_ba = K_ab^T where b's node is the lower)."""
    block = element_k[:, pairs[:, 0], pairs[:, 1]]  # K_ab, a < b locally
    first_is_low = elements[:, pairs[:, 0]] < elements[:, pairs[:, 1]]
    return torch.where(first_is_low[:, :, None, None], block, block.transpose(-1, -2))


def assemble_edges(element_k: torch.Tensor, elements: torch.Tensor, num_nodes: int):
    """Sum element tensors onto edges (deterministically). The vertex tensors K_ii are not
    assembled: the forces use K_ii = -sum_j K_ij (see the module docstring).

    Args:
        element_k: ``[N, n, n, d, d]``; elements: ``[N, n]``.

    Returns:
        edges: ``[Ed, 2]`` (i < j); edge_k: ``[Ed, d, d]`` mapping u_j to the force on i.
    """
    edges, pairs, element_edges = unique_edges(elements, num_nodes)
    return edges, _sum_onto_edges(oriented_blocks(element_k, elements, pairs), element_edges, edges.shape[0])


def assemble_hooke_edges(m, vol, lam, mu, proj, elements: torch.Tensor, num_nodes: int, chunk: int = 1 << 17):
    """``assemble_edges(element_stiffness(m, vol, lam, mu, proj), elements, num_nodes)`` without
    the ``[N, n, n, d, d]`` tensor and its temporaries (each as large as it: the peak of a hooke
    model's construction): the pair blocks ``[chunk, P, d, d]`` of ``chunk`` elements at a time,
    each chunk added onto the edges before the next is made. The same values, bitwise: each
    block is computed alone either way, and each edge's blocks are added in the same order
    (element order; a chunk's blocks of an edge follow the earlier chunks' ones). No gradient
    (the tensor form precomputes)."""
    edges, pairs, element_edges = unique_edges(elements, num_nodes)
    count, dim, num_pairs = elements.shape[0], m.shape[-1], pairs.shape[0]
    flat_edges = element_edges.reshape(-1)
    del element_edges
    slots, num_slots, _ = incidence_slots(flat_edges, edges.shape[0])
    total = m.new_zeros((edges.shape[0], dim, dim))
    with torch.no_grad():
        for start in range(0, count, chunk):
            part = slice(start, start + chunk)
            block = _pair_blocks(m[part], vol[part], lam[part], mu[part], None if proj is None else proj[part],
                                 elements[part], pairs)
            items = slice(start * num_pairs, (start + block.shape[0]) * num_pairs)
            padded_sum(block.reshape(-1, dim, dim), flat_edges[items], slots[items], num_slots, edges.shape[0],
                       out=total)
            del block  # (before the next chunk's is made)
    return edges, total


def _pair_blocks(m, vol, lam, mu, proj, elements, pairs) -> torch.Tensor:
    """``oriented_blocks(element_stiffness(m, vol, lam, mu, proj), elements, pairs)`` ``[N, P, d, d]``
    made for the P pairs alone (not the n x n blocks): K_ab^T is K_ab with a and b swapped, so a
    pair stored from its lower global node is K of (lower, higher) in that order."""
    first_is_low = (elements[:, pairs[:, 0]] < elements[:, pairs[:, 1]])[:, :, None]
    m_a, m_b = m[:, pairs[:, 0]], m[:, pairs[:, 1]]
    low, high = torch.where(first_is_low, m_a, m_b), torch.where(first_is_low, m_b, m_a)  # [N, P, d]
    return stiffness_blocks(low, high, vol, lam, mu, _plane_identity(m, proj))


def _sum_onto_edges(block: torch.Tensor, element_edges: torch.Tensor, num_edges: int) -> torch.Tensor:
    """The pair blocks ``[N, P, d, d]`` summed onto their edges ``[Ed, d, d]`` (``element_edges
    [N, P]``), in a fixed order (deterministic)."""
    flat_edges = element_edges.reshape(-1)
    slots, num_slots, _ = incidence_slots(flat_edges, num_edges)
    return padded_sum(block.reshape(-1, *block.shape[2:]), flat_edges, slots, num_slots, num_edges)


def hooke_edge_partial_forces(u: torch.Tensor, edges: torch.Tensor, edge_k: torch.Tensor) -> torch.Tensor:
    """Partial forces of each edge on its two nodes ``[Ed, 2, d]`` from displacements ``[V, d]``:
    with w = u_j - u_i, -K_ij w on i and K_ij^T w on j (the whole force: no vertex term)."""
    w = u[edges[:, 1]] - u[edges[:, 0]]
    on_low = -torch.einsum("eab,eb->ea", edge_k, w)
    on_high = torch.einsum("eba,eb->ea", edge_k, w)
    return torch.stack([on_low, on_high], dim=1)


def stvk_tensors(m, vol, lam, mu, proj=None):
    """Picinbono's element tensors (B, C, D) with the shapes of the module docstring."""
    b = 0.5 * element_stiffness(m, vol, lam, mu, proj)
    dots = torch.einsum("nja,nka->njk", m, m)  # [N, n, n]
    c = 0.5 * lam[:, None, None, None, None] * dots[:, :, :, None, None] * m[:, None, None, :, :]
    # mu/2 ((m_l.m_j) m_k + (m_l.m_k) m_j), indices [n, j, k, l, a]
    c = c + 0.5 * mu[:, None, None, None, None] * (
        dots.transpose(1, 2)[:, :, None, :, None] * m[:, None, :, None, :]
        + dots[:, None, :, :, None] * m[:, :, None, None, :]
    )
    c = vol[:, None, None, None, None] * c
    d = 0.125 * lam[:, None, None, None, None] * torch.einsum("njk,nlm->njklm", dots, dots)
    d = d + 0.125 * mu[:, None, None, None, None] * (
        torch.einsum("njm,nkl->njklm", dots, dots) + torch.einsum("njl,nkm->njklm", dots, dots)
    )
    d = vol[:, None, None, None, None] * d
    return b, c, d


def stvk_energy(u, b, c, d):
    """Element energies ``[N]`` from displacements ``u [N, n, d]``."""
    gram = torch.einsum("nja,nka->njk", u, u)
    quadratic = torch.einsum("nja,njkab,nkb->n", u, b, u)
    cubic = torch.einsum("njk,njkla,nla->n", gram, c, u)
    quartic = torch.einsum("njklm,njk,nlm->n", d, gram, gram)
    return quadratic + cubic + quartic


def stvk_forces(u, b, c, d):
    """Element forces -dW/du ``[N, n, d]``."""
    gram = torch.einsum("nja,nka->njk", u, u)
    c_dot_u = torch.einsum("npkla,nla->npk", c, u)  # sum_l C_pkl . u_l
    grad = 2.0 * torch.einsum("npkab,nkb->npa", b, u)
    grad = grad + 2.0 * torch.einsum("npk,nka->npa", c_dot_u, u) + torch.einsum("njk,njkpa->npa", gram, c)
    grad = grad + 4.0 * torch.einsum("npklm,nlm,nka->npa", d, gram, u)
    return -grad


def stvk_dforces(u, du, b, c, d):
    """(dF/du) du per element ``[N, n, d]``."""
    gram = torch.einsum("nja,nka->njk", u, u)
    d_gram = torch.einsum("nja,nka->njk", du, u)
    d_gram = d_gram + d_gram.transpose(1, 2)
    c_dot_u = torch.einsum("npkla,nla->npk", c, u)
    c_dot_du = torch.einsum("npkla,nla->npk", c, du)
    grad = 2.0 * torch.einsum("npkab,nkb->npa", b, du)
    grad = grad + 2.0 * (torch.einsum("npk,nka->npa", c_dot_u, du) + torch.einsum("npk,nka->npa", c_dot_du, u))
    grad = grad + torch.einsum("njk,njkpa->npa", d_gram, c)
    d_times_gram = torch.einsum("npklm,nlm->npk", d, gram)
    d_times_dgram = torch.einsum("npklm,nlm->npk", d, d_gram)
    grad = grad + 4.0 * (torch.einsum("npk,nka->npa", d_times_gram, du)
                         + torch.einsum("npk,nka->npa", d_times_dgram, u))
    return -grad

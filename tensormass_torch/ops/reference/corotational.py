"""Corotational linear elasticity (Nesme & Payan 2005; SOFA's TetrahedronFEMForceField "large").

Per element a rotation R is extracted from the deformation gradient F = P + grad U (P the
identity, or the tangent projector of a membrane), and linear elasticity acts on the unrotated
displacement: grad U' = R^T F - P, eps' = P sym(grad U') P, sigma' = lam tr(eps') P + 2 mu eps',
f_j = -vol R sigma' m_j, i.e. f = -R K (R^T x - X). With R held fixed this is the gradient of
W = vol psi(eps'); the differential is R K R^T dx. Shapes as in stress_form: u [N, n, d],
m [N, n, d], vol/lam/mu [N], proj [N, d, d] or None, rotations [N, d, d].
"""
from __future__ import annotations

import torch

from .stress_form import _energy_density, _isotropic, _nodal, _project, _sym, displacement_gradient, small_matmul


def _plane(m, proj):
    d = m.shape[-1]
    return torch.eye(d, dtype=m.dtype, device=m.device).expand(m.shape[0], d, d) if proj is None else proj


def deformation_gradient(u, m, proj=None):
    """F = P + grad U ``[N, d, d]`` (P = I for full-dimensional elements)."""
    return _plane(m, proj) + displacement_gradient(u, m)


def polar_rotations(F: torch.Tensor, rest_normals=None, normals=None, rotations=None) -> torch.Tensor:
    """Rotation factor of the polar decomposition F = R S, a proper rotation (det R = +1) ``[N, d, d]``.

    Inverted elements (det F < 0) get the closest proper rotation: the singular vector of the
    smallest singular value is flipped. For membranes, F maps the rest plane only, so the rest
    normal is mapped onto the current normal first (``rest_normals``, ``normals`` ``[N, 3]``).
    ``rotations``: the factor as already computed (a kernel's, ``[N, d, d]``): its values are
    returned and only the derivative is taken here (no Newton passes, no SVD).
    """
    if rest_normals is not None:
        F = F + normals[:, :, None] * rest_normals[:, None, :]
    return _PolarRotation.apply(F, rotations)


class _PolarRotation(torch.autograd.Function):
    """F -> R, the closest proper rotation (the polar factor where det F > 0), with the polar
    factor's own derivative.

    Forward: 2-D in closed form (the angle of (F00 + F11, F10 - F01)); 3-D by Newton's iteration
    X <- (g X + X^-T / g) / 2 with determinant scaling g = |det X|^(-1/3) (Higham), a fixed count
    of cofactor-and-scale passes over the batch, then the SVD for the elements it does not serve
    (det F <= 0, where the closest proper rotation flips the smallest singular vector, or not
    converged): the SVD of every element is slow as a batch of 3x3 problems on a GPU
    (docs/gradients.md).

    Backward: F = R S turns R by dR = R W, W skew with W S + S W = R^T dF - dF^T R. In 3-D, with
    W = [w]x, the left side is [(tr(S) I - S) w]x, so the vector-Jacobian product is
    dL/dF = 2 R [c]x, c = (tr(S) I - S)^-1 axial(skew(R^T G)); in 2-D, W = w J and the left side
    is w tr(S) J: dL/dF = (B10 - B01) / tr(S) R J with B = R^T G. Unlike the SVD's backward
    (1 / (s_i^2 - s_j^2)) it is finite where singular values repeat (at rest F = I: all equal);
    only a collapsed element (s_i + s_j = 0) has none."""

    generate_vmap_rule = True

    @staticmethod
    def forward(F, known=None):
        return _closest_rotation(F) if known is None else known.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(inputs[0], output)

    @staticmethod
    def backward(ctx, grad, *_):
        F, R = ctx.saved_tensors
        return polar_vjp(F, R, grad), None


def polar_vjp(F: torch.Tensor, R: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    """dL/dF ``[N, d, d]`` for R = polar(F) and dL/dR = ``grad`` (see :class:`_PolarRotation`)."""
    Rt = R.transpose(-1, -2)
    B = small_matmul(Rt, grad)
    S = small_matmul(Rt, F)
    if F.shape[-1] == 2:
        beta = B[..., 1, 0] - B[..., 0, 1]
        trace = _guarded(S[..., 0, 0] + S[..., 1, 1])
        RJ = torch.stack([R[..., :, 1], -R[..., :, 0]], dim=-1)  # R J, J = [[0, -1], [1, 0]]
        return (beta / trace)[..., None, None] * RJ
    S = 0.5 * (S + S.transpose(-1, -2))
    b = 0.5 * _axial(B - B.transpose(-1, -2))
    M = torch.diagonal(S, dim1=-2, dim2=-1).sum(-1)[..., None, None] * torch.eye(3, dtype=F.dtype,
                                                                                device=F.device) - S
    cof = _cofactors(M)  # M symmetric: its adjugate is its cofactor matrix
    c = (cof * b.unsqueeze(-2)).sum(-1) / _guarded(_det_from(M, cof))[..., None]
    return 2.0 * small_matmul(R, _cross_matrix(c))


def _guarded(value: torch.Tensor) -> torch.Tensor:
    """``value`` kept at least the dtype's tiny in magnitude (its sign kept): a divisor."""
    tiny = torch.finfo(value.dtype).tiny
    return torch.where(value.abs() > tiny, value, torch.where(value < 0, -tiny, tiny))


def _axial(W: torch.Tensor) -> torch.Tensor:
    """w of a skew matrix W = [w]x ``[..., 3]``."""
    return torch.stack([W[..., 2, 1], W[..., 0, 2], W[..., 1, 0]], dim=-1)


def _cross_matrix(w: torch.Tensor) -> torch.Tensor:
    """[w]x ``[..., 3, 3]``: [w]x v = w x v."""
    zero = torch.zeros_like(w[..., 0])
    return torch.stack([torch.stack([zero, -w[..., 2], w[..., 1]], -1),
                        torch.stack([w[..., 2], zero, -w[..., 0]], -1),
                        torch.stack([-w[..., 1], w[..., 0], zero], -1)], dim=-2)


def _cofactors(X: torch.Tensor) -> torch.Tensor:
    """The cofactor matrix of 3x3 matrices ``[..., 3, 3]`` (det(X) X^-T): its columns are cross
    products of X's columns."""
    c0, c1, c2 = X[..., :, 0], X[..., :, 1], X[..., :, 2]
    return torch.stack([torch.linalg.cross(c1, c2), torch.linalg.cross(c2, c0), torch.linalg.cross(c0, c1)], dim=-1)


def _det_from(X: torch.Tensor, cofactors: torch.Tensor) -> torch.Tensor:
    return (X[..., :, 0] * cofactors[..., :, 0]).sum(-1)


#: Newton passes of the 3-D polar factor (determinant-scaled, the convergence is quadratic once
#: near: a few passes beyond what moderately stretched elements need); an element it has not
#: converged on (orthogonality error above 100 eps) takes the SVD instead
POLAR_NEWTON_PASSES = 10


def _closest_rotation(F: torch.Tensor) -> torch.Tensor:
    if F.shape[-1] == 2:
        angle = torch.atan2(F[..., 1, 0] - F[..., 0, 1], F[..., 0, 0] + F[..., 1, 1])
        c, s = torch.cos(angle), torch.sin(angle)
        return torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], dim=-2)
    if _traced(F):  # torch.compile, opcheck's fake tensors: no data-dependent branch
        return _svd_rotation(F)
    X = F
    for _ in range(POLAR_NEWTON_PASSES):
        cof = _cofactors(X)
        det = _guarded(_det_from(X, cof))
        scale = det.abs() ** (-1.0 / 3.0)
        X = 0.5 * (scale[..., None, None] * X + cof / (scale * det)[..., None, None])
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    error = (X.transpose(-1, -2) @ X - eye).abs().amax((-2, -1))
    det_f = _det_from(F, _cofactors(F))
    others = ~((det_f > 0) & (error <= 100 * torch.finfo(F.dtype).eps))
    if bool(others.any()):
        X = X.clone()
        X[others] = _svd_rotation(F[others])
    return X


def _traced(t: torch.Tensor) -> bool:
    from torch._subclasses.fake_tensor import is_fake

    return torch.compiler.is_compiling() or is_fake(t)


def _svd_rotation(F: torch.Tensor) -> torch.Tensor:
    U, _, Vh = torch.linalg.svd(F)
    det = torch.linalg.det(U @ Vh)
    flip = torch.ones_like(U[..., 0, :])
    flip[..., -1] = torch.where(det < 0, -1.0, 1.0)
    return (U * flip[..., None, :]) @ Vh


def qr_rotations(x_elem: torch.Tensor, rest_elem: torch.Tensor) -> torch.Tensor:
    """SOFA's "large" frame: axes from the first edge and the normal of the first face.

    x_elem, rest_elem ``[N, n, 3]`` -> R ``[N, 3, 3]`` with R = frame(x)^T frame(X).
    """
    def frame(p):
        ex = p[:, 1] - p[:, 0]
        ez = torch.linalg.cross(ex, p[:, 2] - p[:, 0])
        ey = torch.linalg.cross(ez, ex)
        axes = torch.stack([ex, ey, ez], dim=1)
        return axes / torch.linalg.vector_norm(axes, dim=2, keepdim=True)

    return small_matmul(frame(x_elem).transpose(1, 2), frame(rest_elem))


def _rotated_strain(u, m, rotations, proj):
    F = deformation_gradient(u, m, proj)
    return _project(_sym(rotations.transpose(1, 2) @ F - _plane(m, proj)), proj)


def forces(u, m, vol, lam, mu, rotations, proj=None):
    """Element forces ``[N, n, d]`` for the given rotations."""
    stress = _isotropic(_rotated_strain(u, m, rotations, proj), lam, mu, proj)
    return _nodal(rotations @ stress, m, vol)


def energy(u, m, vol, lam, mu, rotations, proj=None):
    """Element energies ``[N]`` with the rotations held fixed."""
    return vol * _energy_density(_rotated_strain(u, m, rotations, proj), lam, mu)


def dforces(du, m, vol, lam, mu, rotations, proj=None):
    """(dF/du) du with R fixed: -vol R sigma(P sym(R^T grad dU) P) m_j ``[N, n, d]``."""
    d_strain = _project(_sym(rotations.transpose(1, 2) @ displacement_gradient(du, m)), proj)
    return _nodal(rotations @ _isotropic(d_strain, lam, mu, proj), m, vol)

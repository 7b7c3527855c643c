"""Closed-form references for accuracy studies: cantilever beams and Richardson extrapolation.

Everything is in SI units (m, N, Pa, kg, s) and plain float64 (Python floats / numpy), so that a
reference never inherits the precision or the device of the simulation it judges.

The beam is a straight prismatic cantilever of length ``L`` clamped at ``x = 0`` and free at
``x = L``, with small deflections ``w(x)`` (positive along the load) and linear elastic material.
Two theories:

* Euler-Bernoulli: plane sections stay plane and normal to the axis (no shear deformation, no
  rotary inertia).
* Timoshenko: sections stay plane but rotate by ``phi`` independently of the slope ``w'``; the
  shear force is ``Q = kappa G A (w' - phi)`` with a shear coefficient ``kappa``. The clamp holds
  ``w = 0`` and ``phi = 0`` (the slope ``w'(0)`` is free to carry the shear strain).

A 3-D elastic body clamped on its whole end face is stiffer near the clamp than either theory
says (the face cannot warp nor contract), so a converged 3-D solution differs from Timoshenko's
by a fraction of a percent to a few percent at ``L / h = 5``; :func:`richardson` gives the
converged value of the 3-D discretisation itself.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence, Union

import numpy as np
import torch

from ..errors import MaterialError

__all__ = [
    "BETA1_CLAMPED_FREE", "BeamSection", "rectangular_section", "cowper_shear_coefficient",
    "euler_bernoulli_cantilever", "timoshenko_cantilever", "euler_bernoulli_first_frequency",
    "timoshenko_first_frequency", "RichardsonEstimate", "richardson",
]

#: First root of 1 + cos(b) cosh(b) = 0: the clamped-free Euler-Bernoulli beam has its first
#: bending mode at omega_1 = BETA1^2 sqrt(EI / (rho A L^4)).
BETA1_CLAMPED_FREE = 1.8751040687119611

ArrayLike = Union[float, Sequence[float], np.ndarray]


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return value


def _non_negative(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be a non-negative finite number, got {value!r}")
    return value


# ---------------------------------------------------------------------------------------------
# Sections
# ---------------------------------------------------------------------------------------------


def cowper_shear_coefficient(poisson: float) -> float:
    """Shear coefficient kappa of a solid rectangle: Cowper (1966), 10 (1 + nu) / (12 + 11 nu).

    kappa = 5/6 at nu = 0 and 0.8497 at nu = 0.3; it does not depend on the aspect ratio of the
    rectangle in Cowper's derivation.
    """
    nu = float(poisson)
    if not (math.isfinite(nu) and -1.0 < nu < 0.5):
        raise MaterialError(f"poisson must lie in (-1, 0.5), got {poisson!r}")
    return 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu)


@dataclass(frozen=True)
class BeamSection:
    """Stiffness and inertia of a beam cross-section, per unit length.

    Attributes:
        area: A in m^2.
        inertia: second moment of area I about the bending axis, in m^4.
        bending_stiffness: E I in N m^2.
        shear_stiffness: kappa G A in N.
        shear_coefficient: kappa (dimensionless).
        mass_per_length: rho A in kg/m.
        rotary_inertia: rho I in kg m (rotational inertia of the section per unit length).
    """

    area: float
    inertia: float
    bending_stiffness: float
    shear_stiffness: float
    shear_coefficient: float
    mass_per_length: float
    rotary_inertia: float


def rectangular_section(young: float, poisson: float, density: float, width: float, height: float) -> BeamSection:
    """Section of a solid ``width x height`` rectangle bending across its ``height``.

    The load and the deflection are along ``height``: I = width height^3 / 12, and the shear
    coefficient is Cowper's (:func:`cowper_shear_coefficient`), G = E / (2 (1 + nu)).
    """
    young = _positive("young", young)
    density = _positive("density", density)
    width, height = _positive("width", width), _positive("height", height)
    kappa = cowper_shear_coefficient(poisson)
    area = width * height
    inertia = width * height ** 3 / 12.0
    shear_modulus = young / (2.0 * (1.0 + float(poisson)))
    return BeamSection(area=area, inertia=inertia, bending_stiffness=young * inertia,
                       shear_stiffness=kappa * shear_modulus * area, shear_coefficient=kappa,
                       mass_per_length=density * area, rotary_inertia=density * inertia)


# ---------------------------------------------------------------------------------------------
# Static deflection
# ---------------------------------------------------------------------------------------------


def _span(x: ArrayLike, length: float) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(x)) or np.any(x < 0) or np.any(x > length * (1 + 1e-12)):
        raise ValueError(f"x must lie on the span [0, {length}] (measured from the clamp)")
    return x


def euler_bernoulli_cantilever(x: ArrayLike, length: float, bending_stiffness: float,
                               distributed_load: float = 0.0, tip_load: float = 0.0):
    """Euler-Bernoulli deflection ``w(x)`` (m) of a cantilever, same shape as ``x``.

    Args:
        x: positions along the span in m, 0 at the clamp (scalar or array).
        length: L in m.
        bending_stiffness: E I in N m^2.
        distributed_load: q in N/m, uniform over the span (self-weight: rho g A).
        tip_load: P in N at x = L.

    w(x) = q x^2 (6 L^2 - 4 L x + x^2) / (24 EI) + P x^2 (3 L - x) / (6 EI); at the tip
    q L^4 / (8 EI) + P L^3 / (3 EI).
    """
    length = _positive("length", length)
    ei = _positive("bending_stiffness", bending_stiffness)
    x = _span(x, length)
    q, p = float(distributed_load), float(tip_load)
    w = q * x ** 2 * (6 * length ** 2 - 4 * length * x + x ** 2) / (24 * ei) + p * x ** 2 * (3 * length - x) / (6 * ei)
    return float(w) if w.ndim == 0 else w


def timoshenko_cantilever(x: ArrayLike, length: float, bending_stiffness: float, shear_stiffness: float,
                          distributed_load: float = 0.0, tip_load: float = 0.0):
    """Timoshenko deflection ``w(x)`` (m) of a cantilever, same shape as ``x``.

    Euler-Bernoulli's bending part plus the shear part: the shear force Q(x) = q (L - x) + P
    strains the section by Q / (kappa G A), so w_shear(x) = (q (L x - x^2 / 2) + P x) / (kappa G A);
    at the tip q L^2 / (2 kappa G A) + P L / (kappa G A). Args as
    :func:`euler_bernoulli_cantilever`, and ``shear_stiffness`` kappa G A in N.
    """
    length = _positive("length", length)
    kga = _positive("shear_stiffness", shear_stiffness)
    bending = euler_bernoulli_cantilever(x, length, bending_stiffness, distributed_load, tip_load)
    x = _span(x, length)
    q, p = float(distributed_load), float(tip_load)
    shear = (q * (length * x - 0.5 * x ** 2) + p * x) / kga
    w = bending + shear
    return float(w) if np.ndim(w) == 0 else w


# ---------------------------------------------------------------------------------------------
# First bending frequency
# ---------------------------------------------------------------------------------------------


def euler_bernoulli_first_frequency(length: float, bending_stiffness: float, mass_per_length: float) -> float:
    """First bending frequency (Hz) of a clamped-free Euler-Bernoulli beam.

    f_1 = BETA1^2 / (2 pi L^2) sqrt(EI / (rho A)), BETA1 = 1.87510407 (:data:`BETA1_CLAMPED_FREE`).
    """
    length = _positive("length", length)
    ei = _positive("bending_stiffness", bending_stiffness)
    m = _positive("mass_per_length", mass_per_length)
    return BETA1_CLAMPED_FREE ** 2 / (2 * math.pi * length ** 2) * math.sqrt(ei / m)


def _timoshenko_free_end_determinant(omega: float, length: float, ei: float, kga: float, m: float, j: float) -> float:
    """det of the free-end conditions (Q(L) = 0, M(L) = 0) over the solutions with w(0) = phi(0) = 0.

    Harmonic motion of amplitude (w, phi) at angular frequency omega, written in the deflection
    w, the section rotation phi, the shear force Q and the bending moment M:
        w' = phi + Q / (kappa G A),   phi' = M / EI,   Q' = -rho A omega^2 w,   M' = -Q - rho I omega^2 phi.
    In the dimensionless state z = (w, L phi, L^3 Q / EI, L^2 M / EI) over s = x / L this is
    z' = S z with entries 1, EI / (kappa G A L^2), -rho A omega^2 L^4 / EI, -rho I omega^2 L^2 / EI:
    bounded for any slenderness, and exactly Euler-Bernoulli's when the last two parameters of
    the beam are zero. The clamp leaves Q(0), M(0) free; the frequencies are the zeros of the
    determinant of the 2 x 2 block of exp(S) that maps them to (Q(L), M(L)).
    """
    s = torch.zeros(4, 4, dtype=torch.float64)
    s[0, 1] = 1.0
    s[0, 2] = ei / (kga * length ** 2)  # 0 for kga = inf: no shear deformation
    s[1, 3] = 1.0
    s[2, 0] = -m * omega ** 2 * length ** 4 / ei
    s[3, 2] = -1.0
    s[3, 1] = -j * omega ** 2 * length ** 2 / ei
    block = torch.linalg.matrix_exp(s)[2:, 2:]
    return float(block[0, 0] * block[1, 1] - block[0, 1] * block[1, 0])


def timoshenko_first_frequency(length: float, bending_stiffness: float, shear_stiffness: float,
                               mass_per_length: float, rotary_inertia: float = 0.0) -> float:
    """First bending frequency (Hz) of a clamped-free Timoshenko beam.

    Solves the exact frequency equation of the Timoshenko beam (shear deformation, and rotary
    inertia when ``rotary_inertia`` rho I > 0) for its lowest root: the determinant of the
    free-end conditions over the clamped solutions (a 4 x 4 matrix exponential) is scanned up
    from zero and bisected to float64 precision. ``rotary_inertia = 0`` gives the shear-only
    correction; ``shear_stiffness = math.inf`` gives Rayleigh's beam, and with no rotary inertia
    Euler-Bernoulli's. Shear and rotary inertia only lower the frequency,
    so the root lies below :func:`euler_bernoulli_first_frequency`.

    Args: L (m), EI (N m^2), kappa G A (N), rho A (kg/m), rho I (kg m).
    """
    length = _positive("length", length)
    ei = _positive("bending_stiffness", bending_stiffness)
    kga = float(shear_stiffness)
    if not kga > 0:  # math.inf is allowed: no shear deformation
        raise ValueError(f"shear_stiffness must be positive (math.inf for none), got {shear_stiffness!r}")
    m = _positive("mass_per_length", mass_per_length)
    j = _non_negative("rotary_inertia", rotary_inertia)
    omega_eb = 2 * math.pi * euler_bernoulli_first_frequency(length, ei, m)

    def det(omega):
        return _timoshenko_free_end_determinant(omega, length, ei, kga, m, j)

    grid = np.linspace(1e-3, 1.0 + 1e-6, 100) * omega_eb
    values = [det(w) for w in grid]
    for lo, hi, f_lo, f_hi in zip(grid[:-1], grid[1:], values[:-1], values[1:]):
        if f_lo == 0.0:
            return lo / (2 * math.pi)
        if f_lo * f_hi < 0:
            break
    else:
        raise ValueError("no Timoshenko root found below the Euler-Bernoulli frequency: check the section values")
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        f_mid = det(mid)
        if f_mid == 0.0 or hi - lo <= 4 * np.finfo(float).eps * hi:
            break
        if f_lo * f_mid < 0:
            hi = mid
        else:
            lo, f_lo = mid, f_mid
    return 0.5 * (lo + hi) / (2 * math.pi)


# ---------------------------------------------------------------------------------------------
# Richardson extrapolation
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RichardsonEstimate:
    """The h -> 0 limit of a sequence of refinements f(h) = value + C h^order.

    Attributes:
        value: the extrapolated limit.
        order: the observed convergence order p (or the one given).
        error_estimate: |value - f(finest h)|, the error left in the finest value.
    """

    value: float
    order: float
    error_estimate: float


def _order_ratio(p: float, h1: float, h2: float, h3: float) -> float:
    """(h1^p - h2^p) / (h2^p - h3^p) for h1 > h2 > h3 > 0: increasing in p."""
    return (h1 ** p - h2 ** p) / (h2 ** p - h3 ** p)


def richardson(values: Sequence[float], hs: Sequence[float], order: float = None) -> RichardsonEstimate:
    """Extrapolate refinements ``values[i] = f(hs[i])`` to h -> 0, assuming f(h) = f0 + C h^p.

    Args:
        values: the computed quantities, one per refinement ``[n]``.
        hs: the mesh sizes (or time steps) ``[n]``, positive and distinct, in any order.
        order: the convergence order p if known; None estimates it from the three finest values
            (needs n >= 3), by solving (f1 - f2) / (f2 - f3) = (h1^p - h2^p) / (h2^p - h3^p).

    Only the finest values are used: the three finest for the order, the two finest for the
    limit f0 = f2 + (f2 - f1) h2^p / (h1^p - h2^p) (f1 at the coarser h1). A sequence of the
    assumed form is recovered exactly. Non-monotone (oscillating) or diverging sequences are not
    in the asymptotic range and raise ValueError.
    """
    values = np.asarray(values, dtype=np.float64).reshape(-1)
    hs = np.asarray(hs, dtype=np.float64).reshape(-1)
    if values.shape != hs.shape:
        raise ValueError(f"richardson: {values.size} values but {hs.size} mesh sizes")
    need = 2 if order is not None else 3
    if values.size < need:
        purpose = " to estimate the order" if order is None else ""
        raise ValueError(f"richardson needs at least {need} refinements{purpose}, got {values.size}")
    if not (np.all(np.isfinite(values)) and np.all(np.isfinite(hs)) and np.all(hs > 0)):
        raise ValueError("richardson: values must be finite and mesh sizes positive and finite")
    by_size = np.argsort(-hs)
    hs, values = hs[by_size], values[by_size]
    if np.any(np.diff(hs) == 0):
        raise ValueError("richardson: mesh sizes must be distinct")
    if order is None:
        (h1, h2, h3), (f1, f2, f3) = hs[-3:], values[-3:]
        if f2 == f3:
            return RichardsonEstimate(float(f3), math.inf, 0.0)
        target = (f1 - f2) / (f2 - f3)
        lo, hi = 1e-3, 1.0
        if not target > _order_ratio(lo, h1, h2, h3):
            raise ValueError(f"richardson: the differences {f1 - f2:.3e}, {f2 - f3:.3e} do not shrink "
                             "monotonically: the refinements are not in the asymptotic range")
        while _order_ratio(hi, h1, h2, h3) < target:
            hi *= 2.0
            if hi > 64:
                raise ValueError("richardson: observed order above 64; the sequence has converged to rounding")
        for _ in range(200):  # bisection: the ratio is monotone in p
            mid = 0.5 * (lo + hi)
            if _order_ratio(mid, h1, h2, h3) < target:
                lo = mid
            else:
                hi = mid
        order = 0.5 * (lo + hi)
    else:
        order = _positive("order", order)
    (h1, h2), (f1, f2) = hs[-2:], values[-2:]
    value = f2 + (f2 - f1) * h2 ** order / (h1 ** order - h2 ** order)
    return RichardsonEstimate(float(value), float(order), float(abs(value - f2)))

"""Local quadric patches: nested height-field models around a point, and closest points on them.

The curvature-aware estimator (:mod:`hapticloud.core.perception.curvature`) fits these; the
models go from a plane to a full quadric (:data:`QUADRIC_MODELS`), all from one QR factorisation.
Inputs are centred and scaled as in :mod:`.fits`; degenerate systems give ``valid=False``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import lapack

from ..errors import InputError
from ..validation import as_points, as_vector3
from ._lsq import (
    _EZ,
    _MIN_SLOPE_DEN,
    MAX_COND,
    FloatArray,
    _as_weights,
    _finite_float,
    _frozen,
)
from .rotations import rotation_between

# ----- local quadric patch -----------------------------------------------------------------------

#: Models of :func:`quadric_patch`, simplest first, with the monomials each one uses.
QUADRIC_MODELS: dict[str, tuple[str, ...]] = {
    "plane": ("1", "x", "y"),
    "paraboloid": ("1", "x", "y", "xx", "xy", "yy"),
    "spheroid": ("1", "x", "y", "xx", "xy", "yy", "zz"),
    "quadric": ("1", "x", "y", "xx", "xy", "yy", "zz", "xz", "yz"),
}


def _monomial_rows(q: FloatArray, k: int, zhat: FloatArray | None = None) -> FloatArray:
    """``(k + 1, N)``: the first ``k`` of ``1, x, y, x², xy, y², z², xz, yz``, then ``z``.

    ``zhat`` stands for ``z`` inside the monomials (see :class:`NestedQuadricLSQ`).
    """
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    zm = z if zhat is None else zhat
    rows = np.empty((k + 1, len(q)))
    rows[k] = z
    products = ((x, x), (x, y), (y, y), (zm, zm), (x, zm), (y, zm))
    for i in range(k):
        if i == 0:
            rows[0] = 1.0
        elif i < 3:
            rows[i] = x if i == 1 else y
        else:
            u, v = products[i - 3]
            np.multiply(u, v, out=rows[i])
    return rows


def quadric_matrices(coef: ArrayLike) -> tuple[FloatArray, FloatArray, float]:
    """``(A, b, c)`` of ``F(q) = q^T A q + b . q + c`` for the coefficients of ``z = f(x, y, z)``.

    ``coef`` holds the coefficients of ``1, x, y, x², xy, y², z², xz, yz``; ``F = f - z``.
    """
    c0, cx, cy, cxx, cxy, cyy, czz, cxz, cyz = (float(v) for v in np.asarray(coef).reshape(9))
    a = np.array(
        [
            [cxx, 0.5 * cxy, 0.5 * cxz],
            [0.5 * cxy, cyy, 0.5 * cyz],
            [0.5 * cxz, 0.5 * cyz, czz],
        ]
    )
    return a, np.array([cx, cy, -1.0]), c0


def paraboloid_height(q: FloatArray, coef: FloatArray) -> FloatArray:
    """``c0 + cx x + cy y + cxx x² + cxy xy + cyy y²`` at local points ``q`` (local units)."""
    x, y = q[:, 0], q[:, 1]
    c = coef
    return c[0] + x * (c[1] + c[3] * x + c[4] * y) + y * (c[2] + c[5] * y)


def quadric_height(q: FloatArray, coef: FloatArray) -> FloatArray:
    """Height ``z`` of the surface ``z = f(x, y, z)`` above each local point's ``(x, y)``.

    The root of ``czz z² + (cxz x + cyz y - 1) z + P(x, y) = 0`` that continues the height field
    through the origin (the stable form ``2P / (1 - L + sqrt((1 - L)² - 4 czz P))``); where the
    vertical line misses the surface (past its silhouette) the discriminant is clipped at 0.
    """
    p = paraboloid_height(q, coef)
    one_minus_l = 1.0 - coef[7] * q[:, 0] - coef[8] * q[:, 1]
    disc = np.maximum(one_minus_l * one_minus_l - 4.0 * coef[6] * p, 0.0)
    den = one_minus_l + np.sqrt(disc)
    safe = np.abs(den) > 1e-12
    return np.where(safe, 2.0 * p / np.where(safe, den, 1.0), p)


class NestedQuadricLSQ:
    """Weighted least squares of ``z = f(x, y, z)`` for all nested models from one QR.

    Low-level (no validation): ``q`` is ``(N, 3)`` finite, already in the fit's frame and of order
    one; ``weights`` ``(N,)`` non-negative. The columns ``1, x, y | x², xy, y² | z² | xz, yz`` are
    weighted, equilibrated and factorised once together with ``z`` (``[A | z] = QR``). The leading
    ``k x k`` block of ``R`` and the first ``k`` entries of its last column solve the model made of
    the first ``k`` columns, and the squares of the remaining entries sum to that model's
    residual: every model of :data:`QUADRIC_MODELS` then costs a triangular solve, and comparing
    them (:meth:`rss`) costs nothing.

    ``response`` (optional, ``(N,)``) replaces ``z`` as the left-hand side (Gauss-Newton steps).
    ``zhat`` (optional, ``(N,)``) replaces the measured ``z`` inside the ``z²``, ``xz``, ``yz``
    columns by a smooth prediction of it (e.g. a paraboloid fitted first). With the measured
    ``z`` on both sides the fit can explain noise with itself: on flat data ``z (1 - c x) = 0``,
    a pair of planes, fits better than the plane. With a prediction the extra columns are
    (nearly) in the span of the quadratic ones on flat data, so the conditioning check rejects
    them, and on curved data they carry the fourth-order shape without errors-in-variables bias.
    """

    def __init__(
        self,
        q: FloatArray,
        weights: FloatArray,
        k_max: int = 9,
        zhat: FloatArray | None = None,
        response: FloatArray | None = None,
    ) -> None:
        n = len(q)
        k_max = min(k_max, max(n - 1, 0))
        aug = _monomial_rows(q, k_max, zhat)  # rows = columns of [A | z]: aug.T Fortran-ordered
        if response is not None:
            aug[k_max] = response
        aug *= np.sqrt(weights)
        norms = np.sqrt(np.einsum("ij,ij->i", aug, aug))
        norm_list = norms.tolist()
        usable = next((i for i in range(k_max) if not norm_list[i] > 0.0), k_max)
        self.usable = usable  # models stop at the first empty column
        self.norms = norms[:usable]
        self.r = np.zeros((1, 1))
        self._tail = np.zeros(1)
        if usable == 0 or not math.isfinite(norm_list[k_max]):
            self.usable = 0
            return
        if usable < k_max:
            aug = np.vstack((aug[:usable], aug[k_max:]))
        aug[:usable] *= (1.0 / self.norms)[:, None]
        # LAPACK's QR straight on the Fortran-ordered transpose: no copy, no Q formed. Only the
        # upper triangle of the leading block is read below (R); the rest holds reflectors.
        qr_packed, _, _, info = lapack.dgeqrf(aug.T, overwrite_a=True)
        r = qr_packed[: usable + 1]
        # A NaN anywhere reaches the last column's last entry (the response is reduced last).
        if info != 0 or not (math.isfinite(r[-1, -1]) and math.isfinite(r[0, 0])):
            self.usable = 0
            return
        self.r = r
        self._tail = r[:, -1] ** 2  # the last column lies on or above the diagonal

    def rss(self, model: str) -> float:
        """Weighted residual sum of squares of ``z`` for ``model`` (inf if it cannot be fitted)."""
        k = len(QUADRIC_MODELS[model])
        if k > self.usable or k >= self.r.shape[0]:
            return np.inf
        return float(self._tail[k:].sum())

    def solve(self, model: str, max_cond: float = MAX_COND) -> tuple[FloatArray | None, float]:
        """``(coef, cond)``: the 9 coefficients (unused ones 0), or None when ill-conditioned.

        ``cond`` is LAPACK's 1-norm estimate for the triangular factor (within a factor of the
        model's size of the 2-norm condition number of the equilibrated system).
        """
        k = len(QUADRIC_MODELS[model])
        if k > self.usable or k >= self.r.shape[0]:
            return None, np.inf
        rk = self.r[:k, :k]
        rcond, info = lapack.dtrcon(rk, norm="1", uplo="U")
        cond = 1.0 / rcond if info == 0 and rcond > 0.0 else np.inf
        if not cond <= max_cond:
            return None, cond
        sol, info = lapack.dtrtrs(rk, self.r[:k, -1])
        coef = np.zeros(9)
        coef[:k] = sol / self.norms[:k]
        return (coef, cond) if info == 0 and np.all(np.isfinite(coef)) else (None, cond)

    def leverage(self, model: str, point: FloatArray, zhat: float | None = None) -> float:
        """``sqrt(x0ᵀ (AᵀWA)⁻¹ x0)`` of ``model`` at one local ``point`` (its monomials ``x0``):
        the standard error of the fitted height there, in units of the residual scale (inf if
        the model cannot be fitted).

        With weights that are not inverse variances (a spatial kernel of at most 1) this is an
        upper bound of the sandwich estimate. ``zhat`` stands for the point's ``z`` in the
        z-terms, as the fit's ``zhat`` did for the data. Approximate for models with z-terms:
        the linear design's, not that of the heights' Gauss-Newton refinement, and along the
        fit's local z, not the surface normal.
        """
        k = len(QUADRIC_MODELS[model])
        if k > self.usable or k >= self.r.shape[0]:
            return math.inf
        q = np.asarray(point, dtype=np.float64).reshape(1, 3)
        row = _monomial_rows(q, k, None if zhat is None else np.array([zhat]))[:k, 0]
        v, info = lapack.dtrtrs(self.r[:k, :k], row / self.norms[:k], trans=1)
        lev = math.sqrt(float(v @ v)) if info == 0 else math.inf
        return lev if math.isfinite(lev) else math.inf


def fit_local_quadric(
    q: FloatArray, weights: FloatArray, model: str, *, max_cond: float = MAX_COND
) -> tuple[FloatArray | None, float]:
    """One model of :class:`NestedQuadricLSQ`: ``(coef or None, cond)`` (local units)."""
    k = len(QUADRIC_MODELS[model])
    return NestedQuadricLSQ(q, weights, k).solve(model, max_cond)


def refine_quadric_heights(
    q: FloatArray, w: FloatArray, coef: FloatArray, model: str, iterations: int
) -> FloatArray:
    """Gauss-Newton on the heights ``z - H(x, y; θ)`` of a model with z-terms (local units).

    Low-level (no validation), for the coefficients ``coef`` of ``model`` first solved with a
    paraboloid's prediction of z in the z-terms: that prediction misses exactly the fourth-order
    shape those terms are there for. Here the model's own explicit height ``H`` (the root of the
    quadratic in z, :func:`quadric_height`) is fitted to the measured heights, each residual
    weighted by ``1 / (1 + |∇H|²)`` (vertical to normal distance, to first order):
    ``∂H/∂θ = m(x, y, H) / D`` with ``D = 1 - 2 czz H - cxz x - cyz y``, so a step is one weighted
    solve of the same nested structure. A step is kept only if it lowers the weighted squared
    residual. Exact on an exact model and free of errors-in-variables bias: no measured z is
    among the regressors.

    Returns
    -------
    numpy.ndarray
        The refined 9 coefficients (``coef`` itself if no step helped).
    """
    k = len(QUADRIC_MODELS[model])
    x, y, z = q[:, 0], q[:, 1], q[:, 2]
    quad = _monomial_rows(q, 6)[:6]  # 1, x, y, x², xy, y²: fixed, so built once
    basis = np.column_stack((np.ones(len(q)), x, y, z))  # last column: the heights below

    def geometric(c: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, float]:
        p = c[:6] @ quad
        lin = c[7] * x + c[8] * y if k > 7 else 0.0
        one_minus_l = 1.0 - lin
        root = one_minus_l + np.sqrt(np.maximum(one_minus_l * one_minus_l - 4.0 * c[6] * p, 0.0))
        height = 2.0 * p / np.where(np.abs(root) > 1e-12, root, 1.0)
        # Clipped: near a silhouette (vertical tangent) the height's derivative blows up.
        den = np.maximum(one_minus_l - 2.0 * c[6] * height, _MIN_SLOPE_DEN)
        basis[:, 3] = height
        slope = basis @ np.array(
            [[c[1], c[2]], [2.0 * c[3], c[4]], [c[4], 2.0 * c[5]], [c[7], c[8]]]
        )
        # Vertical -> normal distance, to first order: weight by 1 / (1 + |∇H|²).
        wg = w / (1.0 + np.einsum("ij,ij->i", slope, slope) / (den * den))
        r = z - height
        return height, den, wg, float(wg @ (r * r))

    height, den, wg, cost = geometric(coef)
    for _ in range(iterations):
        lsq = NestedQuadricLSQ(q, wg / (den * den), k, height, (z - height) * den)
        delta, _ = lsq.solve(model)
        if delta is None:
            break
        trial = coef + delta
        t_height, t_den, t_wg, t_cost = geometric(trial)
        if not t_cost < cost:
            break
        done = t_cost > cost * (1.0 - 1e-6)
        coef, height, den, wg, cost = trial, t_height, t_den, t_wg, t_cost
        if done:
            break
    return coef


def local_quadric_distance(q: FloatArray, coef: FloatArray) -> FloatArray:
    """Signed first-order (Sampson) distances ``-F / |∇F|`` of local points (local units).

    Positive on the ``+z`` side; exact for a plane, close to the geometric distance where the
    surface is smooth on the scale of the distance.
    """
    a, b, c = quadric_matrices(coef)
    grad = q @ (2.0 * a) + b
    # F = q.A.q + b.q + c = q.(grad + b) / 2 + c
    f_val = 0.5 * np.einsum("ij,ij->i", q, grad + b) + c
    gnorm = np.sqrt(np.einsum("ij,ij->i", grad, grad))
    return -f_val / np.maximum(gnorm, 1e-12)


def local_quadric_closest(coef: FloatArray, h: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """Closest point to ``h`` on the local quadric and the unit normal there (local units).

    The normal is ``-∇F / |∇F|`` (the ``+z`` side near the origin). ``None`` when no closest
    point is found (see :meth:`QuadricPatch.closest_point`).
    """
    c0, cx, cy, cxx, cxy, cyy, czz, cxz, cyz = (float(v) for v in coef)
    a = ((cxx, 0.5 * cxy, 0.5 * cxz), (0.5 * cxy, cyy, 0.5 * cyz), (0.5 * cxz, 0.5 * cyz, czz))
    b = (cx, cy, -1.0)
    found = _closest_on_quadric(a, b, c0, (float(h[0]), float(h[1]), float(h[2])))
    if found is None:
        return None
    q = found
    grad = [-(2.0 * (a[i][0] * q[0] + a[i][1] * q[1] + a[i][2] * q[2]) + b[i]) for i in range(3)]
    norm = math.sqrt(grad[0] ** 2 + grad[1] ** 2 + grad[2] ** 2)
    if not (norm > 0.0 and math.isfinite(norm)):
        return None
    return np.array(q), np.array(grad) / norm


def _sym_eigen(
    a: tuple[tuple[float, ...], ...],
) -> tuple[list[float], list[tuple[float, float, float]]]:
    """Eigenvalues and unit eigenvectors of a symmetric 3x3 matrix (tuples of floats).

    A matrix without ``z`` couplings (plane, paraboloid: third row zero) is diagonalised in
    closed form by one Jacobi rotation; anything else goes to LAPACK.
    """
    if a[0][2] == 0.0 and a[1][2] == 0.0 and a[2][2] == 0.0:
        p, r, s = a[0][0], a[0][1], a[1][1]
        theta = 0.5 * math.atan2(2.0 * r, p - s)
        cs, sn = math.cos(theta), math.sin(theta)
        mu1 = p * cs * cs + 2.0 * r * sn * cs + s * sn * sn
        mu2 = p * sn * sn - 2.0 * r * sn * cs + s * cs * cs
        return [mu1, mu2, 0.0], [(cs, sn, 0.0), (-sn, cs, 0.0), (0.0, 0.0, 1.0)]
    mu, vecs = np.linalg.eigh(np.array(a))
    cols = vecs.T.tolist()
    return mu.tolist(), [(v[0], v[1], v[2]) for v in cols]


def _closest_on_quadric(
    a: tuple[tuple[float, ...], ...],
    b: tuple[float, float, float],
    c: float,
    h: tuple[float, float, float],
    iters: int = 60,
) -> list[float] | None:
    """Closest point to ``h`` on ``q.A.q + b.q + c = 0`` (plain floats: 3-vectors are faster so)."""
    mu, vecs = _sym_eigen(a)
    eta = [v[0] * h[0] + v[1] * h[1] + v[2] * h[2] for v in vecs]
    beta = [v[0] * b[0] + v[1] * b[1] + v[2] * b[2] for v in vecs]
    tiny = 1e-12 * max(1.0, max(abs(m) for m in mu))
    lo = max([-0.5 / m for m in mu if m > tiny], default=-math.inf)
    hi = min([-0.5 / m for m in mu if m < -tiny], default=math.inf)

    def phi(lam: float) -> tuple[float, float, list[float]]:
        val, slope, p = c, 0.0, [0.0, 0.0, 0.0]
        for i in range(3):
            den = 1.0 + 2.0 * lam * mu[i]
            pi = (eta[i] - lam * beta[i]) / den
            g = 2.0 * mu[i] * pi + beta[i]
            val += (mu[i] * pi + beta[i]) * pi
            slope -= g * g / den
            p[i] = pi
        return val, slope, p

    lam = 0.0
    val, slope, p = phi(lam)
    # Keep a bracket [left, right] with phi(left) > 0 > phi(right): phi decreases on (lo, hi).
    left, right = (lam, hi) if val > 0.0 else (lo, lam)
    scale = 1.0 + max(abs(v) for v in eta)
    tol = 1e-13 * (abs(c) + scale)
    for _ in range(iters):
        if abs(val) <= tol:
            break
        new = lam - val / slope if slope < 0.0 else math.nan
        if not left < new < right:  # also catches NaN
            if math.isfinite(left) and math.isfinite(right):
                new = 0.5 * (left + right)
            elif math.isfinite(left):  # grow to the right until phi changes sign
                new = left + 2.0 * max(1.0, abs(left))
            else:
                new = right - 2.0 * max(1.0, abs(right))
        lam = new
        val, slope, p = phi(lam)
        if not math.isfinite(val):
            return None
        if val > 0.0:
            left = lam
        else:
            right = lam
        if right - left <= 1e-15 * (1.0 + abs(lam)):
            break
    if not abs(val) <= 1e-6 * scale:
        return None
    q = [vecs[0][i] * p[0] + vecs[1][i] * p[1] + vecs[2][i] * p[2] for i in range(3)]
    return q if all(math.isfinite(v) for v in q) else None


@dataclass(frozen=True)
class QuadricPatch:
    """A local surface ``z = f(x, y, z)`` in a frame at ``origin`` with axes ``frame`` (columns).

    The surface is the zero set of ``F(q) = q^T A q + b . q + c`` in scaled local coordinates
    ``q = frame^T (p - origin) / scale_m``, with ``b_z = -1``: a height field over the frame's
    ``x, y`` plane (``"plane"``, ``"paraboloid"``), optionally with a ``z²`` term (``"spheroid"``:
    exact for spheres and circular cylinders touching the origin's tangent plane) or ``z²``,
    ``xz``, ``yz`` terms (``"quadric"``: any quadric). Because ``|∇F| ≈ 1`` near the origin, the
    algebraic residual is close to the geometric one there.

    ``coef`` holds the coefficients of ``1, x, y, x², xy, y², z², xz, yz`` (unused ones 0);
    ``rms_m`` is the weighted RMS residual (m) and ``cond`` the condition number of the fit.
    """

    valid: bool
    origin: FloatArray
    frame: FloatArray
    scale_m: float
    model: str
    coef: FloatArray
    rms_m: float
    cond: float
    n_points: int = 0
    reason: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", _frozen(self.origin))
        object.__setattr__(self, "frame", _frozen(self.frame, np.eye(3)))
        object.__setattr__(self, "coef", _frozen(self.coef, np.zeros(9)))
        object.__setattr__(self, "rms_m", _finite_float(self.rms_m))

    @property
    def n_params(self) -> int:
        """Number of fitted coefficients."""
        return len(QUADRIC_MODELS.get(self.model, ()))

    def to_local(self, points: ArrayLike) -> FloatArray:
        """Scaled local coordinates ``(N, 3)`` of world ``points``."""
        p = as_points(points, "points")
        return ((p - self.origin) @ self.frame) / self.scale_m

    def residuals(self, points: ArrayLike) -> FloatArray:
        """Signed distances (m) of ``points`` to the surface, positive on the ``+z`` side."""
        return self.scale_m * local_quadric_distance(self.to_local(points), self.coef)

    def closest_point(self, point: ArrayLike) -> tuple[bool, FloatArray, FloatArray]:
        """The surface point closest to ``point`` and the unit normal there (world, m).

        Solves the Lagrange conditions ``q - h + λ ∇F(q) = 0``, ``F(q) = 0`` through the secular
        equation in the eigenbasis of ``A``, on the interval where ``I + 2 λ A`` is positive
        definite: there the equation is monotone, its root unique and the global minimiser
        (safeguarded Newton with bisection). ``ok=False`` (with the frame's origin and axis) when
        the patch is invalid, no such root exists or the iteration fails.
        """
        h = self.to_local(np.reshape(as_vector3(point, "point"), (1, 3)))[0]
        found = local_quadric_closest(self.coef, h) if self.valid else None
        if found is None:
            return False, self.origin.copy(), self.frame[:, 2].copy()
        q, n = found
        return True, self.origin + self.scale_m * (self.frame @ q), self.frame @ n


def quadric_patch(
    points: ArrayLike,
    weights: ArrayLike | None = None,
    *,
    origin: ArrayLike,
    normal: ArrayLike,
    model: str = "paraboloid",
    scale_m: float | None = None,
    max_cond: float = MAX_COND,
    refine_steps: int = 5,
) -> QuadricPatch:
    """Fit a local surface ``z = f(x, y, z)`` in a frame at ``origin``, ``z`` along ``normal``.

    Parameters
    ----------
    points
        ``(N, 3)`` points (m); NaN/inf rows dropped.
    weights
        Optional ``(N,)`` non-negative weights (robust x spatial, chosen by the caller).
    origin
        Frame origin (m), e.g. the current closest-point estimate.
    normal
        Frame ``z`` axis (any length), e.g. the current normal estimate.
    model
        One of :data:`QUADRIC_MODELS`: ``"plane"``, ``"paraboloid"``, ``"spheroid"``, ``"quadric"``.
    scale_m
        Length that divides the local coordinates (m); default the points' RMS distance to the
        origin. Choose the neighbourhood's size: the coefficients are then of order one.
    max_cond
        Largest accepted condition number of the equilibrated system.
    refine_steps
        Gauss-Newton steps for the z-terms of ``"spheroid"`` and ``"quadric"``
        (:func:`refine_quadric_heights`).

    Returns
    -------
    QuadricPatch
        ``valid=False`` with a reason for too few points (the model's coefficients plus one),
        points all at the origin or an ill-conditioned system.

    Raises
    ------
    InputError
        For a wrong shape/dtype (naming the argument) or an unknown ``model``.
    """
    if model not in QUADRIC_MODELS:
        raise InputError(f"model = {model!r}: must be one of {', '.join(QUADRIC_MODELS)}")
    o = as_vector3(origin, "origin")
    frame = rotation_between(_EZ, as_vector3(normal, "normal"))
    p = as_points(points, "points")
    w = _as_weights(weights, p.shape[0])
    keep = np.isfinite(p).all(axis=1)
    if w is not None:
        keep &= np.isfinite(w) & (w > 0.0)
    p = p[keep]
    w = np.ones(len(p)) if w is None else w[keep]
    n = len(p)

    def invalid(reason: str, scale: float = 1.0, cond: float = np.inf) -> QuadricPatch:
        return QuadricPatch(False, o, frame, scale, model, np.zeros(9), 0.0, cond, n, reason)

    n_coef = len(QUADRIC_MODELS[model])
    if n < n_coef + 1:
        return invalid(f"{model} needs {n_coef + 1} points, got {n}")
    local = (p - o) @ frame
    if scale_m is None:
        scale = float(np.sqrt(np.mean(np.einsum("ij,ij->i", local, local))))
    else:
        scale = float(scale_m)
    if not (np.isfinite(scale) and scale > 0.0):
        return invalid("all points at the origin: no scale")
    q = local / scale
    wn = w / w.mean()
    k = len(QUADRIC_MODELS[model])
    lsq = NestedQuadricLSQ(q, wn, min(k, 6))
    coef, cond = lsq.solve(model if k <= 6 else "paraboloid", max_cond)
    if coef is not None and k > 6:
        # z-terms: a paraboloid's prediction of z first, then the model's own heights.
        coef, cond = NestedQuadricLSQ(q, wn, k, paraboloid_height(q, coef)).solve(model, max_cond)
        if coef is not None:
            coef = refine_quadric_heights(q, wn, coef, model, refine_steps)
    if coef is None:
        return invalid(f"ill-conditioned {model} fit (cond {cond:.3g})", scale, cond)
    res = local_quadric_distance(q, coef)
    rms = scale * float(np.sqrt((wn @ (res * res)) / n))
    return QuadricPatch(True, o, frame, scale, model, coef, rms, cond, n)

"""Stage E: from the cleaned cloud around the HIP to the closest surface point and its normal.

Three estimators share one result type (:class:`SurfaceFit`) and one entry point
(:func:`estimate_surface`, dispatching on ``AbstractionConfig.method``):

- ``"paper"``: the paper's Alg. 2, concentric shells around the HIP (this module);
- ``"quadric"``: a robust local quadric surface and its exact closest point
  (:mod:`.curvature`; the default: the shells' circle centres sit inside curved surfaces);
- ``"nearest"``: the naive baseline, the nearest point and a local plane (:mod:`.nearest`).

Normal convention everywhere: unit, pointing out of the surface, towards the camera (and so the
HIP's side); ``d_proj = (c - h) . (-n) - r_hip`` is then the signed free distance.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..config import StageConfig, nested, param
from ..errors import ConfigError
from ..geometry.fits import circle3d, plane3d
from ..geometry.rotations import orient_normal
from ..haptics.distance import d_proj
from ..validation import as_points, as_unit_vector3, as_vector3, drop_nonfinite
from .estimate import ShellFit

FloatArray = NDArray[np.float64]

_ZERO3 = np.zeros(3)
_ZERO3.setflags(write=False)
_UP = np.array([0.0, 0.0, 1.0])
_UP.setflags(write=False)

METHODS = ("paper", "quadric", "nearest")


# ----- parameters --------------------------------------------------------------------------------


#: The narrowest Gaussian bandwidth a fit may use (m), after its narrowings too.
MIN_BANDWIDTH_M = 0.005


@dataclass(frozen=True)
class QuadricConfig(StageConfig):
    """The curvature-aware estimator (``method = "quadric"``, :mod:`.curvature`)."""

    model: str = param(
        "auto",
        choices=("auto", "plane", "paraboloid", "spheroid", "quadric"),
        doc="surface model; auto picks the simplest the points support (BIC)",
    )
    bandwidth_m: float = param(
        0.035,
        lo=MIN_BANDWIDTH_M,
        hi=0.2,
        unit="m",
        doc="Gaussian spatial weight around the closest point",
    )
    n_refits: int = param(2, lo=1, hi=10, doc="fits, each re-centred on the previous closest point")
    shape_iterations: int = param(
        2, lo=0, hi=20, doc="Gauss-Newton steps refining the z-terms of spheroid/quadric"
    )
    robust: str = param(
        "tukey", choices=("tukey", "huber", "none"), doc="robust weight function (IRLS)"
    )
    robust_k: float = param(
        4.685, lo=1.0, hi=20.0, doc="robust tuning constant, in units of the residual scale"
    )
    noise_floor_m: float = param(
        0.0005, lo=1e-5, hi=0.02, unit="m", log_scale=True, doc="lower bound of the residual scale"
    )
    bic_penalty: float = param(
        0.5, lo=0.0, hi=20.0, doc="model-selection penalty per coefficient, x log(n)"
    )
    max_extrapolation_m: float = param(
        0.06, lo=0.005, hi=0.2, unit="m", doc="closest point farther from all points: fall back"
    )
    min_points: int = param(12, lo=4, hi=10000, doc="fewer points in r_out: fall back")
    max_points: int = param(
        800, lo=20, hi=100000, doc="about this many points (thinned evenly) are used (speed)"
    )
    coarse_points: int = param(
        400, lo=20, hi=100000, doc="points used by the refits before the last (speed)"
    )
    fallback: str = param(
        "paper", choices=("paper", "none"), doc="what answers when the surface fit fails"
    )
    second_surface: bool = param(
        True,
        doc="points nearer the HIP than the fit allows: fit them as a second surface, take the "
        "nearer (creases, bodies touching)",
    )
    second_surface_sigmas: float = param(
        4.0,
        lo=1.0,
        hi=20.0,
        doc="points this many residual scales nearer than the fitted surface (or off it) belong "
        "to another surface",
    )
    second_surface_min_m: float = param(
        0.0015,
        lo=0.0,
        hi=0.05,
        unit="m",
        doc="and at least this much nearer than the fitted surface",
    )
    second_surface_min_points: int = param(
        16, lo=1, hi=10000, doc="fewer such nearer points: noise (flying pixels), not a surface"
    )
    narrow_below_quality: float = param(
        0.5,
        lo=0.0,
        hi=1.0,
        doc="a fit of lower quality is tried again with half the bandwidth (an edge or a step "
        "inside it); the better one answers",
    )
    narrowings: int = param(
        1,
        lo=0,
        hi=3,
        doc="how many times the bandwidth may be halved (never below the narrowest, 5 mm)",
    )


@dataclass(frozen=True)
class AbstractionConfig(StageConfig):
    """Stage E parameters: which estimator, its neighbourhood and its shells."""

    method: str = param("quadric", choices=METHODS, doc="surface estimator")
    r_in_m: float = param(
        0.04, lo=0.001, hi=1.0, unit="m", doc="innermost sphere r_0 (paper, fixed shells)"
    )
    r_out_m: float = param(
        0.15, lo=0.005, hi=1.0, unit="m", doc="outer sphere: only points within it are used"
    )
    n_shells: int = param(4, lo=1, hi=50, doc="shells between r_0 and r_out (paper)")
    shell_mode: str = param(
        "adaptive",
        choices=("fixed", "adaptive"),
        doc="fixed: r_0=r_in .. r_out; adaptive: shells start at the nearest point",
    )
    adaptive_span_m: float = param(
        0.02, lo=0.001, hi=1.0, unit="m", doc="adaptive shells cover [d_min, d_min + span]"
    )
    min_shell_points: int = param(6, lo=3, hi=10000, doc="fewer points: shell skipped")
    reject_fraction: float = param(
        0.5, lo=0.0, hi=0.9, doc="fraction of shell estimates rejected (worst normals)"
    )
    nearest_k: int = param(20, lo=3, hi=1000, doc="neighbours of the nearest point (plane)")
    quadric: QuadricConfig = nested(QuadricConfig)

    def check(self) -> None:
        if not self.r_in_m < self.r_out_m:
            raise ConfigError(f"r_in_m = {self.r_in_m}: must be below r_out_m = {self.r_out_m}")


# ----- result ------------------------------------------------------------------------------------


def _vec(value: ArrayLike) -> tuple[FloatArray, bool]:
    arr = np.array(value, dtype=np.float64).reshape(-1)
    return arr, arr.shape == (3,) and bool(np.all(np.isfinite(arr)))


@dataclass(frozen=True)
class SurfaceFit:
    """Closest surface point ``centroid`` (m, world) and unit ``normal`` for one HIP.

    When ``valid`` is False, ``centroid`` and ``normal`` are finite placeholders and ``reason``
    says why. ``quality`` (0..1) says how much to trust a valid estimate; ``shells`` lists the
    paper method's per-shell fits (empty for the others); ``model`` names the surface model the
    quadric estimator chose (or what it fell back to); ``surfaces`` is 2 when the points held two
    surfaces (a crease) and the nearer one was taken, with ``reason`` saying so on a valid fit.
    """

    valid: bool
    centroid: FloatArray
    normal: FloatArray
    reason: str = ""
    shells: tuple[ShellFit, ...] = ()
    quality: float = 0.0
    method: str = ""
    model: str = ""
    n_points: int = 0
    #: 2 when the points held two surfaces and the nearer was taken (``reason`` says how).
    surfaces: int = 1
    #: The fit's residual scale (m; robust, at the points it kept): how noisy the points the
    #: estimate stands on were. 0 when the method measures none (the paper's shells).
    residual_m: float = 0.0
    #: Standard error (m) of the fitted surface's height at the closest point (the model's own
    #: prediction uncertainty there: large where the points leave it to extrapolate). 0 when
    #: the method has no error model (the paper's shells, the nearest point).
    height_se_m: float = 0.0
    #: Share of the points near the fitted surface that its robust weights kept (1 when the
    #: method weighs none): a fit that keeps a minority models part of what it was given.
    inliers: float = 1.0

    def __post_init__(self) -> None:
        c, ok_c = _vec(self.centroid)
        n, ok_n = _vec(self.normal)
        norm = float(np.linalg.norm(n)) if ok_n else 0.0
        ok_n = ok_n and norm > 1e-12
        c = c if ok_c else _ZERO3.copy()
        n = n / norm if ok_n else _UP.copy()
        c.setflags(write=False)
        n.setflags(write=False)
        object.__setattr__(self, "centroid", c)
        object.__setattr__(self, "normal", n)
        if self.valid and not (ok_c and ok_n):
            object.__setattr__(self, "valid", False)
            object.__setattr__(self, "reason", self.reason or "non-finite centroid or normal")
        q = float(self.quality)
        object.__setattr__(self, "quality", min(1.0, max(0.0, q)) if np.isfinite(q) else 0.0)
        r = float(self.residual_m)
        object.__setattr__(self, "residual_m", r if np.isfinite(r) and r > 0.0 else 0.0)
        se = float(self.height_se_m)
        object.__setattr__(self, "height_se_m", se if np.isfinite(se) and se > 0.0 else 0.0)
        object.__setattr__(self, "shells", tuple(self.shells))

    def d_proj(self, hip: ArrayLike, r_hip_m: float) -> float:
        """Signed free distance ``(c - h) . (-n) - r_hip`` (m); negative means penetration."""
        return d_proj(self.centroid, self.normal, hip, r_hip_m)

    @classmethod
    def invalid(cls, reason: str, **extra: object) -> SurfaceFit:
        """An invalid fit with placeholder vectors and ``reason``."""
        return cls(False, _ZERO3, _UP, reason, **extra)  # type: ignore[arg-type]


# ----- inputs ------------------------------------------------------------------------------------


def prepare_inputs(
    points_world: ArrayLike, hip: ArrayLike, camera_axis: ArrayLike, r_out_m: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Validate the arguments; return the finite points within ``r_out_m`` of the HIP.

    Raises
    ------
    InputError
        (a ``ValueError``) naming ``points_world``, ``hip`` or ``camera_axis``.
    """
    pts = drop_nonfinite(as_points(points_world, "points_world"))
    h = as_vector3(hip, "hip")
    z = as_unit_vector3(camera_axis, "camera_axis")
    if len(pts):
        rel = pts - h
        pts = pts[np.einsum("ij,ij->i", rel, rel) < r_out_m * r_out_m]
    return pts, h, z


# ----- the paper's Alg. 2 ------------------------------------------------------------------------


def shell_edges(distances: FloatArray, cfg: AbstractionConfig) -> FloatArray:
    """Radii ``0 <= r_-1 < r_0 < ... < r_out`` bounding the shells (m).

    ``fixed``: the ball ``(0, r_in)`` then ``n_shells`` equal shells up to ``r_out``.
    ``adaptive``: ``n_shells`` equal shells from the nearest points' distance ``d_min`` to
    ``min(r_out, d_min + adaptive_span_m)``, so the first shell always holds the nearest points.
    ``d_min`` skips the nearest 0.5 % of the points: a flying pixel in front of the surface
    would otherwise open a shell of outliers.
    """
    if cfg.shell_mode == "fixed" or len(distances) == 0:
        outer = np.linspace(cfg.r_in_m, cfg.r_out_m, cfg.n_shells + 1)
        return np.concatenate(([0.0], outer))
    k = min(len(distances) - 1, len(distances) // 200)
    d_min = float(np.partition(distances, k)[k])
    start = max(0.0, d_min * (1.0 - 1e-9) - 1e-12)
    stop = min(cfg.r_out_m, start + cfg.adaptive_span_m)
    if not stop > start:
        stop = cfg.r_out_m
    return np.linspace(start, stop, cfg.n_shells + 1)


def _shell_fit(
    pts: FloatArray, hip: FloatArray, cam: FloatArray, lo: float, hi: float, first: bool
) -> ShellFit:
    n = len(pts)
    if first:
        fit = plane3d(pts)
        kind, center, normal, radius, ok = "plane", fit.centroid, fit.normal, 0.0, fit.valid
    else:
        circ = circle3d(pts)
        kind, center, normal, radius = "circle", circ.center, circ.normal, circ.radius_m
        # A circle on the sphere of radius hi around the HIP has its centre and radius inside it.
        ok = circ.valid and radius <= 1.5 * hi and float(np.linalg.norm(center - hip)) <= 1.5 * hi
    if ok:
        normal = orient_normal(normal, cam, center, hip)
    return ShellFit(lo, hi, kind, center, normal, n, bool(ok), radius_m=radius if ok else 0.0)


def concentric_shells(
    points: FloatArray, hip: FloatArray, camera_axis: FloatArray, cfg: AbstractionConfig
) -> SurfaceFit:
    """The paper's Alg. 2 on points already validated and cropped to ``r_out`` (m, world).

    Shell ``i`` holds the points with ``r_(i-1) < |p - h| < r_i``; the first shell with at least
    ``min_shell_points`` points is fitted with a plane, every further one with a 3D circle; each
    normal is turned to face the camera; the worst ``reject_fraction`` of the estimates (largest
    sum of normal distances to the others) is rejected; the rest are averaged with weights
    ``1 / r_i``.
    """
    n_pts = len(points)
    if n_pts == 0:
        return SurfaceFit.invalid("no points within r_out", method="paper")
    rel = points - hip
    dist = np.sqrt(np.einsum("ij,ij->i", rel, rel))
    edges = shell_edges(dist, cfg)
    shells: list[ShellFit] = []
    seen_first = False
    for lo, hi in pairwise(edges.tolist()):
        inside = points[(dist > lo) & (dist < hi)]
        if len(inside) == 0:
            continue
        if len(inside) < cfg.min_shell_points:
            shells.append(
                ShellFit(
                    lo, hi, "circle" if seen_first else "plane", _ZERO3, _UP, len(inside), False
                )
            )
            continue
        shells.append(_shell_fit(inside, hip, camera_axis, lo, hi, not seen_first))
        seen_first = True
    good = [i for i, s in enumerate(shells) if s.valid]
    if not good:
        return SurfaceFit.invalid(
            "no shell gave a valid fit", shells=tuple(shells), method="paper", n_points=n_pts
        )
    normals = np.array([shells[i].normal for i in good])
    spread = np.sqrt(((normals[:, None, :] - normals[None, :, :]) ** 2).sum(-1)).sum(1)
    n_keep = max(1, len(good) - int(np.floor(cfg.reject_fraction * len(good))))
    kept = sorted(good[j] for j in np.argsort(spread, kind="stable")[:n_keep])
    weights = np.array([1.0 / shells[i].r_outer_m for i in kept])
    centers = np.array([shells[i].center for i in kept])
    kept_normals = np.array([shells[i].normal for i in kept])
    centroid = weights @ centers / weights.sum()
    nsum = weights @ kept_normals
    norm = float(np.linalg.norm(nsum))
    final = [
        ShellFit(
            s.r_inner_m,
            s.r_outer_m,
            s.kind,
            s.center,
            s.normal,
            s.n_points,
            s.valid,
            kept=i in kept,
            radius_m=s.radius_m,
        )
        for i, s in enumerate(shells)
    ]
    if not norm > 1e-9:
        return SurfaceFit.invalid(
            "shell normals cancel out", shells=tuple(final), method="paper", n_points=n_pts
        )
    normal = nsum / norm
    agreement = float(np.clip(kept_normals @ normal, 0.0, 1.0).mean())
    quality = agreement**4 * min(1.0, len(good) / 3.0)
    return SurfaceFit(True, centroid, normal, "", tuple(final), quality, "paper", "shells", n_pts)


# ----- entry point -------------------------------------------------------------------------------


def estimate_surface(
    points_world: ArrayLike,
    hip: ArrayLike,
    camera_axis: ArrayLike,
    cfg: AbstractionConfig | None = None,
) -> SurfaceFit:
    """Estimate the surface point closest to the HIP and its normal (stage E).

    Parameters
    ----------
    points_world
        ``(N, 3)`` cloud in the world frame (m); NaN/inf rows are dropped, points farther than
        ``cfg.r_out_m`` from the HIP ignored.
    hip
        HIP position (m, world).
    camera_axis
        The camera's viewing direction (from the camera into the scene); orients the normal.
    cfg
        Parameters; ``cfg.method`` picks the estimator. Default: the shipped (tuned) ones.

    Returns
    -------
    SurfaceFit
        Never raises on degenerate geometry: too few points, collinear or flat shells and
        ill-conditioned fits give ``valid=False`` (or a fallback estimate with lower quality).

    Raises
    ------
    InputError
        (a ``ValueError``) for a wrong shape or dtype, naming the argument.

    Examples
    --------
    >>> import numpy as np
    >>> xy = np.stack(np.meshgrid(np.linspace(-0.1, 0.1, 41), np.linspace(-0.1, 0.1, 41)), -1)
    >>> cloud = np.column_stack((xy.reshape(-1, 2), np.zeros(41 * 41)))   # the plane z = 0
    >>> fit = estimate_surface(cloud, hip=[0.0, 0.0, 0.06], camera_axis=[0.0, 0.0, -1.0])
    >>> fit.valid, fit.model, float(fit.normal[2]), round(fit.d_proj([0.0, 0.0, 0.06], 0.04), 6)
    (True, 'plane', 1.0, 0.02)
    """
    cfg = AbstractionConfig() if cfg is None else cfg
    pts, h, z = prepare_inputs(points_world, hip, camera_axis, cfg.r_out_m)
    if cfg.method == "paper":
        return concentric_shells(pts, h, z, cfg)
    # Imported here: those modules build on SurfaceFit and the configs defined above.
    if cfg.method == "nearest":
        from .nearest import nearest_point

        return nearest_point(pts, h, z, cfg.nearest_k)
    from .curvature import quadric_surface

    return quadric_surface(pts, h, z, cfg)

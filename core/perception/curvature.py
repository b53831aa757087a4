"""The curvature-aware estimator: a robust local quadric and its exact closest point to the HIP.

The paper's shells replace the surface by ring circles whose centres lie inside a curved surface
(10-16 mm deep on a head-sized sphere). Here the surface itself is modelled near the closest
point and the closest point is computed on the model:

1. start from a plane through the points nearest the HIP, normal facing the camera;
2. in the frame at the current closest-point estimate (z along its normal), fit
   ``z = f(x, y, z)`` by weighted least squares: Gaussian weights of width ``bandwidth_m``
   around the estimate times robust (Tukey/Huber) weights from the previous residuals. The
   model is the simplest of plane / paraboloid / spheroid (+z², exact for spheres and
   cylinders) / quadric (+z², xz, yz) that the points support (BIC, all four from one QR);
   the z-terms use a paraboloid's prediction of z, then Gauss-Newton on the model's own
   heights (no measured z among the regressors: no errors-in-variables bias, no spurious
   pair-of-planes fits);
3. move to the exact closest point of that surface to the HIP (secular equation) and its normal;
   repeat 2-3 (``n_refits``): re-centring the weights on the closest point reduces the
   higher-order bias; the refits before the last use a coarse subset and the paraboloid;
4. check the answer: a closest point on the near sheet, a surface that stays one height field
   over the hidden region around it, a closest point within ``max_extrapolation_m`` of the
   data. A model failing a check gives way to the next simpler one; if all fail, the paper's
   shells answer (``model="shells"``, half the quality) or the result is flagged invalid.

Because the model extrapolates smoothly, the closest point may lie in a region the end effector
hides: the points around it carry the curvature. Known limit: structure the models cannot
follow inside the bandwidth (an edge, a step between two surfaces) is smoothed over; the robust
weights then reject part of the points and ``quality`` drops with the inlier fraction.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from ..geometry.fits import RANK_TOL
from ..geometry.quadric import (
    QUADRIC_MODELS,
    NestedQuadricLSQ,
    local_quadric_closest,
    local_quadric_distance,
    paraboloid_height,
    quadric_height,
    refine_quadric_heights,
)
from ..geometry.rotations import EDGE_ON_COS, frame_from_unit_normal
from .abstraction import (
    MIN_BANDWIDTH_M,
    AbstractionConfig,
    QuadricConfig,
    SurfaceFit,
    concentric_shells,
)

FloatArray = NDArray[np.float64]

_MAD_TO_SIGMA = 1.4826
# Spatial weights below exp(-0.5 * 3^2) ~ 0.011 are dropped from the fit (speed).
_SUPPORT_SIGMAS = 3.0
_MODEL_ORDER = tuple(QUADRIC_MODELS)  # simplest first
_CANDIDATE_MARGIN_M = 0.02
_SECTORS = 36
# The closest point's normal must stay within ~75° of the frame's: else it sits on another sheet.
_MIN_NORMAL_COS = 0.25
# Height-field check of spheroid/quadric fits: D = -dF/dz below this counts as folded.
_MIN_SHEET_DEN = 0.2
# Probes around the closest point (centre and two rings, in units of its gap to the data).
_PROBE_RING = np.vstack(
    [np.zeros((1, 2))]
    + [
        r * np.column_stack((np.cos(a), np.sin(a)))
        for r, a in (
            (0.5, np.linspace(0, 2 * np.pi, 8, endpoint=False)),
            (1.0, np.linspace(0, 2 * np.pi, 12, endpoint=False)),
        )
    ]
)


def _robust_weights(res: FloatArray, scale: float, cfg: QuadricConfig) -> FloatArray:
    if cfg.robust == "none":
        return np.ones_like(res)
    u = np.abs(res) / (cfg.robust_k * scale)
    if cfg.robust == "huber":
        return 1.0 / np.maximum(u, 1.0)
    return np.where(u < 1.0, (1.0 - u * u) ** 2, 0.0)


def _robust_scale(res: FloatArray, floor: float) -> float:
    """Residual scale (m) from the median absolute residual, floored at the noise level."""
    if len(res) == 0:
        return floor
    mid = len(res) // 2
    mad = float(np.partition(np.abs(res), mid)[mid])
    return max(_MAD_TO_SIGMA * mad, floor)


def _fallback(
    points: FloatArray,
    hip: FloatArray,
    cam: FloatArray,
    cfg: AbstractionConfig,
    reason: str,
) -> SurfaceFit:
    n = len(points)
    if cfg.quadric.fallback == "paper":
        fit = concentric_shells(points, hip, cam, cfg)
        if fit.valid:
            return SurfaceFit(
                True,
                fit.centroid,
                fit.normal,
                f"fallback to shells: {reason}",
                fit.shells,
                0.5 * fit.quality,
                "quadric",
                "shells",
                n,
            )
        reason = f"{reason}; shells: {fit.reason}"
    return SurfaceFit.invalid(reason, method="quadric", n_points=n)


def _face_camera(normal: FloatArray, cam: FloatArray, to_hip: FloatArray) -> FloatArray:
    """Alg. 2's sign rule (``orient_normal``) without argument checks, for the inner loop."""
    nz = float(normal @ cam)
    if abs(nz) < EDGE_ON_COS:
        side = float(normal @ to_hip)
        if side != 0.0:
            return normal if side > 0.0 else -normal
    return -normal if nz > 0.0 else normal


class _Fit(NamedTuple):
    """One surface fitted to HIP-relative points (m): its closest point ``origin``, unit
    ``normal``, the model, the residual ``scale`` (m) and inlier share of the last robust pass,
    and what the quality and the second-surface check need (candidates, weights, frame, coef)."""

    origin: FloatArray
    normal: FloatArray
    model: str
    scale: float
    inliers: float
    cand: FloatArray
    robust: FloatArray
    frame: FloatArray
    frame_origin: FloatArray
    coef: FloatArray
    #: Standard error of the fitted height at the closest point, per unit residual scale.
    leverage: float = math.inf


def quadric_surface(
    points: FloatArray, hip: FloatArray, camera_axis: FloatArray, cfg: AbstractionConfig
) -> SurfaceFit:
    """The curvature-aware estimate on points already validated and cropped to ``r_out`` (m).

    Parameters
    ----------
    points
        ``(N, 3)`` finite points within ``cfg.r_out_m`` of the HIP (world frame, m).
    hip
        HIP (m).
    camera_axis
        Unit viewing direction; the normal is turned to face the camera.
    cfg
        Stage parameters; ``cfg.quadric`` holds this estimator's knobs.

    Returns
    -------
    SurfaceFit
        ``model`` names the chosen surface model; ``quality`` in 0..1 combines the inlier
        fraction, the residual level against the noise floor and how well the data surround the
        closest point. Falls back to the paper's shells (``model="shells"``) when the fit fails.
        ``surfaces`` is 2 when points of a second surface lay nearer the HIP than the first fit
        (a crease, two bodies touching): the estimate is then the nearer one (``reason`` says
        which), never a blend of the two.
    """
    qc = cfg.quadric
    n = len(points)
    if n < qc.min_points:
        return _fallback(points, hip, camera_axis, cfg, f"{n} points < min_points {qc.min_points}")
    # Everything relative to the HIP (at 0): far from the world origin nothing loses precision.
    # A uniform subsample of about max_points is all the fits below use (speed).
    rel = points[:: max(1, n // qc.max_points)] - hip
    d2 = np.einsum("ij,ij->i", rel, rel)
    # Every point relative to the HIP, once: the second-surface check of each fit and the fit
    # across a hole count every point, not the subsample.
    every = points - hip
    d2_every = np.einsum("ij,ij->i", every, every)
    best: _Answer | str = ""
    # An edge or a step inside the bandwidth is smoothed over and the fit loses quality: a
    # narrower bandwidth models only the surface near the closest point. Each narrower level is
    # tried first from the patch around the nearest point alone (a HIP equally near two bodies
    # has both in its shell of nearest points), then from that whole shell.
    levels = [lv for lv in range(1, qc.narrowings + 1) if qc.bandwidth_m / 2**lv >= MIN_BANDWIDTH_M]
    tries = [(0, False)] + [(level, seeded) for level in levels for seeded in (True, False)]
    answers: dict[tuple[int, bool], _Answer | str] = {}
    for level, seeded in tries:
        narrowed = qc if level == 0 else _narrowed(qc, level)
        wide = qc if level > 0 else None
        result = _quadric_fit(every, d2_every, hip, rel, d2, camera_axis, narrowed, seeded, wide)
        answers[level, seeded] = result
        if isinstance(result, str):
            best = best or result
            if level == 0:
                break  # no wide fit: the fallback answers (a narrower one alone is not checked)
        elif isinstance(best, str):
            best = result
        elif result.estimate.quality > best.estimate.quality and (
            result.estimate.residual_m < _NARROWED_RESIDUAL * best.estimate.residual_m
            or (
                best.estimate.inliers < _MINORITY
                and result.estimate.inliers >= _NARROWED_MIN_INLIERS
            )
        ):
            # Structure smoothed over leaves the narrower fit with a much smaller residual;
            # noise (a far body) does not, and fewer points would only make it noisier. A wider
            # fit that kept only a minority of its points (three surfaces at a corner: chin,
            # neck, chest) has its residual from that minority, so it cannot be compared; a
            # narrower fit that explains nearly all of its own points answers instead (noise
            # leaves a narrower fit's points as scattered as the wider one's).
            best = result
        if not isinstance(best, str) and best.estimate.quality >= qc.narrow_below_quality:
            break
    if isinstance(best, str):
        return _fallback(points, hip, camera_axis, cfg, best)
    if not levels:
        return _held_no_farther(best.estimate, _unmodelled_nearer_m(best.unmodelled, qc), hip)
    estimate = _nearer_across_a_hole(
        best.estimate, every, d2_every, hip, rel, d2, camera_axis, qc, levels[0]
    )
    if not best.nearer_points:
        return estimate
    patch_key = (levels[0], True)
    if patch_key not in answers:
        narrowed = _narrowed(qc, levels[0])
        answers[patch_key] = _quadric_fit(
            every, d2_every, hip, rel, d2, camera_axis, narrowed, True, qc
        )
    wide_fit = answers[0, False]
    if not isinstance(wide_fit, _Answer):  # unreachable: the loop ended in the fallback then
        return estimate
    estimate = _nearest_patch_if_nearer(estimate, answers[patch_key], wide_fit.own_scale_m, hip)
    return _held_no_farther(estimate, _unmodelled_nearer_m(best.unmodelled, qc), hip)


class _Answer(NamedTuple):
    """One fit's estimate, and what the rules after the narrowing loop need to know of it."""

    estimate: SurfaceFit
    #: The fit's own residual scale (m), before the second-surface check held it at the noise.
    own_scale_m: float
    #: Points lay nearer the HIP than the fitted surface by more than the noise: they made a
    #: second surface, or none of their own.
    nearer_points: bool
    #: Such points that made no surface (HIP-relative, ``(N, 3)``; empty: none). Only the
    #: answer that wins bounds the final one (:func:`_held_no_farther`).
    unmodelled: FloatArray


def _nearest_patch_if_nearer(
    estimate: SurfaceFit, patch: _Answer | str, wide_scale_m: float, hip: FloatArray
) -> SurfaceFit:
    """``estimate``, or the narrower fit from the patch of nearest points (``patch``) if that
    puts the surface clearly nearer. Asked where the second-surface check found points nearer
    than the fitted surface (:attr:`_Answer.nearer_points`).

    Where a fit runs over a step it cannot follow (a strap on the chest, 4-10 mm high), the
    strap's top is taken as a second surface that, fitted with the step's sides, sags below the
    top, or the top alone fails the second surface's inlier test and the fit that kept the plate
    stands; the fit started from the nearest points models the top. It answers if nearer by
    more than ``_PATCH_GAIN_SCALES`` x the wide fit's own residual scale (``wide_scale_m``): on
    noise alone the patch is nearer by a fraction of that (a plane with 4 mm of noise: 0.2 mm),
    and the nearer of two noisy answers would only be biased. Never farther. ``bench
    perception``'s thin-step table: the worst strap (10 x 20 mm) +7.5 -> +3.6 mm at worst, bias
    +1.29 -> +0.23 mm (docs/benchmarks.md). Its quality can be lower than the wide fit's (down
    to 0.5 on straps): where under the loop's ``min_quality`` the camera's estimate is dropped
    for the frame, never replaced by the farther one.
    """
    if isinstance(patch, str) or not patch.estimate.valid:
        return estimate
    nearer = estimate.d_proj(hip, 0.0) - patch.estimate.d_proj(hip, 0.0)
    if not nearer > _PATCH_GAIN_SCALES * wide_scale_m:
        return estimate
    note = f"nearest patch's surface {nearer:.4f} m nearer"
    return dataclasses.replace(
        patch.estimate,
        reason="; ".join(r for r in (estimate.reason, patch.estimate.reason, note) if r),
        surfaces=2,
    )


#: A closest point farther than this many bandwidths from every point lies in a hole (the end
#: effector hides the surface under the HIP): 8.75 mm at the default 35 mm.
_HOLE_BANDWIDTHS = 0.25


def _nearer_across_a_hole(
    best: SurfaceFit,
    every: FloatArray,
    d2_every: FloatArray,
    hip: FloatArray,
    rel: FloatArray,
    d2: FloatArray,
    camera_axis: FloatArray,
    qc: QuadricConfig,
    level: int,
) -> SurfaceFit:
    """``best`` moved toward the HIP where it bridges a hole over structure it smooths.

    A fit across a hole stands on the points around it. Where those hold structure the model
    cannot follow (a cheek bulging from the head, seen past the hand) its residual is many times
    the noise, and across the hole it can pass the bulge on the far side: 3-17 mm on the demo's
    right45 camera (its second camera until the tenth session), with a quality over the gate
    (docs/benchmarks.md). A narrower fit from the patch of nearest points follows the bulge.
    So: closest point in a hole, the fit's residual more than ``second_surface_sigmas`` x the
    local noise (:func:`_patch_noise` on every point, at least the floor), and a narrower fit
    that explains its own points better (residual under ``_NARROWED_RESIDUAL`` x) and puts the
    surface nearer: the answer moves along its normal to that distance. Never farther. On a
    smooth body the residual is the noise and nothing moves (a narrower fit extrapolated from a
    small patch moved a head's surface 9 mm nearer and the hand bounced off it).
    """
    origin = best.centroid - hip
    off = rel - origin
    gap = float(np.sqrt(np.min(np.einsum("ij,ij->i", off, off))))
    if not gap > _HOLE_BANDWIDTHS * qc.bandwidth_m:
        return best
    if not best.residual_m > qc.second_surface_sigmas * qc.noise_floor_m:
        return best  # under the noise floor's bound: the noise need not be measured
    # Only here, past the gates: the noise on every point (the fits use a subsample).
    noise = _patch_noise(every, d2_every, qc)
    if not best.residual_m > qc.second_surface_sigmas * noise:
        return best
    fit = _fit_surface(rel, d2, camera_axis, _narrowed(qc, level), seeded=True, with_leverage=False)
    if isinstance(fit, str) or not fit.scale < _NARROWED_RESIDUAL * best.residual_m:
        return best
    nearer = float(np.sqrt(origin @ origin)) - float(np.sqrt(fit.origin @ fit.origin))
    if not nearer > 0.0:
        return best
    note = (
        f"moved {nearer * 1e3:.1f} mm nearer across a {gap * 1e3:.0f} mm hole: the fit's "
        f"residual {best.residual_m * 1e3:.1f} mm is {best.residual_m / noise:.0f}x the noise, "
        f"a narrower fit's surface is nearer"
    )
    return _moved_nearer(best, nearer, note)


def _moved_nearer(estimate: SurfaceFit, by_m: float, note: str) -> SurfaceFit:
    """``estimate`` moved ``by_m`` (m, > 0) toward the HIP along its normal, ``note`` added to
    its reason."""
    return dataclasses.replace(
        estimate,
        centroid=estimate.centroid + by_m * estimate.normal,
        reason=f"{estimate.reason}; {note}" if estimate.reason else note,
    )


@functools.lru_cache(maxsize=16)
def _narrowed(qc: QuadricConfig, level: int) -> QuadricConfig:
    """``qc`` with its bandwidth halved ``level`` times; built once per configuration (building
    one validates every field: ~130 us, on every low-quality frame otherwise)."""
    return dataclasses.replace(qc, bandwidth_m=qc.bandwidth_m / 2**level)


def _quadric_fit(
    every: FloatArray,
    d2_every: FloatArray,
    hip: FloatArray,
    rel: FloatArray,
    d2: FloatArray,
    camera_axis: FloatArray,
    qc: QuadricConfig,
    seeded: bool = False,
    wide: QuadricConfig | None = None,
) -> _Answer | str:
    """Steps 1-4 at ``qc.bandwidth_m``: the estimate, or a string saying why there is none.

    ``every``, ``d2_every``: every point relative to the HIP and its squared distance (the
    second-surface check counts them all); ``rel``, ``d2``: the subsample the fits use.
    ``wide``: the configuration this one narrows (``None`` for the wide fit itself); a narrower
    fit does not extrapolate farther than its bandwidth. ``seeded``: start from the patch around
    the nearest point only, and answer only if the points that fit leaves out make no nearer
    surface at the ``wide`` configuration."""
    fit = _fit_surface(rel, d2, camera_axis, qc, seeded)
    if isinstance(fit, str):
        return fit
    if seeded and wide is not None:
        nearer = _rest_nearer(fit, rel, d2, camera_axis, qc, wide)
        if nearer:
            return nearer
    surfaces, note, nearer_points, own_scale, unmodelled = 1, "", False, fit.scale, _NONE
    if qc.second_surface:
        fit, surfaces, note, nearer_points, unmodelled = _nearer_surface(
            fit, every, d2_every, rel, d2, camera_axis, qc
        )
    origin, normal, cand, robust = fit.origin, fit.normal, fit.cand, fit.robust

    # 4. Checks: the closest point must be near the data and, for full quality, surrounded by it.
    off = cand - origin
    gap_to_data = float(np.sqrt(np.min(np.einsum("ij,ij->i", off, off))))
    if gap_to_data > qc.max_extrapolation_m:
        return f"closest point {gap_to_data:.3f} m from the data"
    if wide is not None and gap_to_data > qc.bandwidth_m:
        # A narrower fit models the surface within about one bandwidth of its points: across a
        # wider hole (the end effector hides the surface under the HIP) it is a guess.
        return (
            f"narrower fit's closest point {gap_to_data * 1e3:.1f} mm from the data "
            f"> its bandwidth {qc.bandwidth_m * 1e3:.1f} mm"
        )
    inlier = robust > 0.5
    bw = qc.bandwidth_m
    surround = _surround(off[inlier][:: max(1, len(off) // qc.coarse_points)], normal, bw)
    noise_ratio = fit.scale / qc.noise_floor_m
    quality = fit.inliers * surround / (1.0 + 0.01 * noise_ratio * noise_ratio)
    n = len(every)
    height_se = fit.scale * fit.leverage if math.isfinite(fit.leverage) else 0.0
    estimate = SurfaceFit(
        True,
        hip + origin,
        normal,
        note,
        (),
        quality,
        "quadric",
        fit.model,
        n,
        surfaces,
        fit.scale,
        height_se,
        fit.inliers,
    )
    return _Answer(estimate, own_scale, nearer_points, unmodelled)


def _residual_m(fit: _Fit, pts: FloatArray, bw: float) -> FloatArray:
    """Signed distance (m, along the fit's local z) of HIP-relative points ``pts`` from the
    fitted surface at bandwidth ``bw``: positive on the HIP's side."""
    return local_quadric_distance((pts - fit.frame_origin) @ fit.frame * (1.0 / bw), fit.coef) * bw


#: The seeded start's patch: points within this many bandwidths of the nearest point.
_SEED_PATCH_BANDWIDTHS = 1.0


def _fit_surface(
    rel: FloatArray,
    d2: FloatArray,
    camera_axis: FloatArray,
    qc: QuadricConfig,
    seeded: bool = False,
    with_leverage: bool = True,
) -> _Fit | str:
    """Steps 1-3 on HIP-relative points ``rel`` (m) with squared distances ``d2``; a string
    says what failed. ``seeded``: the initial plane from the nearest point's patch only;
    ``with_leverage``: the fit may answer (else its leverage is left inf, not computed)."""
    bw = qc.bandwidth_m
    # 1. Initial plane through the points near the nearest ones (a few skipped: flying pixels).
    k = min(len(rel) - 1, max(2, len(rel) // 200))
    d_near = float(np.sqrt(np.partition(d2, k)[k]))
    cap_mask = d2 < (d_near + bw) ** 2
    if seeded:
        # Only the patch around the nearest points: where two surfaces are equally near the HIP
        # (a medial point between two bodies) the shell of nearest points holds both.
        off_seed = rel - rel[int(np.argpartition(d2, k)[k])]
        patch = _SEED_PATCH_BANDWIDTHS * bw
        cap_mask &= np.einsum("ij,ij->i", off_seed, off_seed) < patch * patch
    cap = rel[cap_mask]
    start = _initial_plane(cap[:: max(1, len(cap) // qc.coarse_points)])
    if start is None:
        return "no plane through the nearest points"
    centroid, normal = start
    normal = _face_camera(normal, camera_axis, -centroid)
    origin = float(centroid @ normal) * normal  # foot of the HIP on that plane

    # The fits look within _SUPPORT_SIGMAS bandwidths of the estimate, which moves by a few mm:
    # a margin keeps one candidate set for all refits. The refits before the last one only
    # move the frame: a coarser subset does that as well, and faster.
    reach = _SUPPORT_SIGMAS * bw + _CANDIDATE_MARGIN_M
    off = rel - origin
    cand = rel[np.einsum("ij,ij->i", off, off) < reach * reach]
    cand = cand[:: max(1, round(len(cand) / qc.max_points))]
    coarse = cand[:: max(1, len(cand) // qc.coarse_points)]
    models = _MODEL_ORDER if qc.model == "auto" else (qc.model,)
    # Frame-moving refits need no fourth-order terms and no model choice: the last one has both.
    coarse_models = ("plane",) if models == ("plane",) else ("paraboloid",)
    robust = np.ones(len(coarse) if qc.n_refits > 1 else len(cand))
    scale, inliers = qc.noise_floor_m, 1.0
    model = models[0]
    for it in range(qc.n_refits):
        last = it == qc.n_refits - 1
        step = _refit(
            cand if last else coarse,
            robust,
            origin,
            normal,
            models if last else coarse_models,
            qc,
            with_leverage=with_leverage and last,
        )
        if isinstance(step, str):
            return step
        origin_new, normal_new, model, frame, coef, leverage = step
        frame_origin = origin
        if not last:
            # Robust weights for the next refit, from this fit's residuals (m).
            nxt = cand if it == qc.n_refits - 2 else coarse
            off = nxt - origin
            res = local_quadric_distance(off @ frame * (1.0 / bw), coef) * bw
            near = np.einsum("ij,ij->i", off, off) < (2.0 * bw) ** 2
            scale = _robust_scale(res[near], qc.noise_floor_m)
            robust = _robust_weights(res, scale, qc)
            inliers = float(np.count_nonzero(robust[near] > 0.5)) / max(1, int(near.sum()))
        origin = origin_new
        normal = _face_camera(normal_new, camera_axis, -origin)
    return _Fit(
        origin, normal, model, scale, inliers, cand, robust, frame, frame_origin, coef, leverage
    )


def _rest_nearer(
    fit: _Fit,
    rel: FloatArray,
    d2: FloatArray,
    camera_axis: FloatArray,
    qc: QuadricConfig,
    wide: QuadricConfig,
) -> str:
    """Why a fit from the nearest patch must not answer ("" if it may).

    A fit started from one patch explains that patch; the other points (another body, the rest
    of a body whose nearest part the end effector hides) are fitted as one surface at the
    ``wide`` bandwidth. If that surface comes nearer the HIP than the patch's, the patch is not
    the nearest surface: the narrow fit gives way (what is not seen may be nearer).
    """
    bw = qc.bandwidth_m
    off = rel - fit.frame_origin
    res = _residual_m(fit, rel, bw)
    near = np.einsum("ij,ij->i", off, off) < (_SUPPORT_SIGMAS * bw) ** 2
    noise = max(fit.scale, qc.noise_floor_m)
    rest = ~(near & (np.abs(res) < qc.second_surface_sigmas * noise))
    if int(np.count_nonzero(rest)) < qc.min_points:
        return ""
    other = _fit_surface(rel[rest], d2[rest], camera_axis, wide, with_leverage=False)
    if isinstance(other, str):
        return ""
    dist = float(np.sqrt(fit.origin @ fit.origin))
    dist_other = float(np.sqrt(other.origin @ other.origin))
    if dist_other < dist - qc.second_surface_min_m:
        return (
            f"the points beside the nearest patch make a surface "
            f"{(dist - dist_other) * 1e3:.1f} mm nearer"
        )
    return ""


#: A narrower fit answers only if its residual scale is below this share of the wider one's,
_NARROWED_RESIDUAL = 0.6
#: or if the wider fit's robust weights kept less than this share of the points near its
#: surface while the narrower one kept at least ``_NARROWED_MIN_INLIERS`` of its own.
_MINORITY = 0.5
_NARROWED_MIN_INLIERS = 0.9
#: A second surface must explain this share of its points at the noise scale (not outliers), or
#: as large a share as the first surface explains of its own where that is less (the scale then
#: under the sensor's noise: :func:`_nearer_surface`).
_MIN_SECOND_INLIERS = 0.7
#: The nearest patch answers if nearer than the wide fit by this many of its residual scales.
_PATCH_GAIN_SCALES = 0.5
#: Refits of each surface at a crease with the robust scale held at the measured noise.
_TIGHT_REFITS = 2


def _tighten(fit: _Fit, noise: float, camera_axis: FloatArray, qc: QuadricConfig) -> _Fit | str:
    """Refit with the robust scale held at the noise of one surface (m).

    Points of two surfaces inflate a fit's own residual scale, so its robust weights keep both
    and the fit runs between them; with the scale of one surface's noise the refits settle on
    the surface most of the points belong to and reject the other.
    """
    bw = qc.bandwidth_m
    models = _MODEL_ORDER if qc.model == "auto" else (qc.model,)
    scale = max(noise, qc.noise_floor_m)
    for it in range(_TIGHT_REFITS):
        off = fit.cand - fit.frame_origin
        robust = _robust_weights(_residual_m(fit, fit.cand, bw), scale, qc)
        last = it == _TIGHT_REFITS - 1
        step = _refit(fit.cand, robust, fit.origin, fit.normal, models, qc, with_leverage=last)
        if isinstance(step, str):
            return step
        origin, normal, model, frame, coef, leverage = step
        near = np.einsum("ij,ij->i", off, off) < (2.0 * bw) ** 2
        inliers = float(np.count_nonzero(robust[near] > 0.5)) / max(1, int(near.sum()))
        fit = _Fit(
            origin,
            _face_camera(normal, camera_axis, -origin),
            model,
            scale,
            inliers,
            fit.cand,
            robust,
            frame,
            fit.origin,
            coef,
            leverage,
        )
    return fit


def _nearer_surface(
    fit: _Fit,
    every: FloatArray,
    d2_every: FloatArray,
    rel: FloatArray,
    d2: FloatArray,
    camera_axis: FloatArray,
    qc: QuadricConfig,
) -> tuple[_Fit, int, str, bool, FloatArray]:
    """The nearer of two surfaces when points lie nearer the HIP than the fitted surface allows.

    No point on the fitted surface is nearer the HIP than its closest point, so points nearer
    than that by more than the noise (``second_surface_sigmas`` x the residual scale, at least
    ``second_surface_min_m``) belong to another surface that the robust fit rejected: a body
    resting on another, the two sides of a crease. The points the first surface does not explain
    are then fitted on their own (both refitted with the robust scale held at the noise, then
    the points segmented once more by which surface explains them), and the nearer of the two
    surfaces answers. Nearer points that fit no surface of their own leave the first fit as it
    is, and where they lie together they bound how far the answer may be
    (:func:`_unmodelled_nearer_m`); scattered ones (outliers, flying pixels) do not.
    Returns the fit that answers, 1 or 2 surfaces, the note, whether points lay nearer than
    the first fit by more than the noise (then :func:`_nearest_patch_if_nearer` is asked too),
    and such points if they make no surface (HIP-relative; empty otherwise).
    """
    dist1 = float(np.sqrt(fit.origin @ fit.origin))
    # Every point counts here, not only the fits' subsample: near a crease the nearer surface
    # may show only a narrow band of points within the margin. The margin is never below its
    # value at the noise floor: too few points within that one, and the noise need not be
    # measured (most frames of a single body; the same answer, about 50 us sooner).
    least = max(qc.second_surface_sigmas * qc.noise_floor_m, qc.second_surface_min_m)
    if dist1 <= least:
        return fit, 1, "", False, _NONE
    if int(np.count_nonzero(d2_every < (dist1 - least) ** 2)) < qc.second_surface_min_points:
        return fit, 1, "", False, _NONE
    noise = _patch_noise(rel, d2, qc)
    margin = max(qc.second_surface_sigmas * noise, qc.second_surface_min_m)
    limit = dist1 - margin
    if limit <= 0.0:
        return fit, 1, "", False, _NONE
    closer = d2_every < limit * limit
    n_closer = int(np.count_nonzero(closer))
    if n_closer < qc.second_surface_min_points:
        return fit, 1, "", False, _NONE
    tight = _tighten(fit, noise, camera_axis, qc)
    if isinstance(tight, _Fit):
        fit = tight
        dist1 = float(np.sqrt(fit.origin @ fit.origin))
    bw = qc.bandwidth_m
    res = _residual_m(fit, every, bw)
    # The other surface lies on the HIP's side of the fit (the fit rejected it, or ran between
    # the two) and, where it matters, nearer the HIP than the first surface's closest point.
    other = (res > qc.second_surface_sigmas * noise) & (d2_every < dist1 * dist1)
    n_other = int(np.count_nonzero(other))
    second = None
    if n_other >= qc.min_points:
        step = max(1, n_other // qc.max_points)
        rel2 = every[other][::step]
        # Tightened next, which computes the leverage of the fit that may answer.
        second = _fit_surface(rel2, d2_every[other][::step], camera_axis, qc, with_leverage=False)
        if isinstance(second, _Fit):
            second = _tighten(second, noise, camera_axis, qc)
        if isinstance(second, _Fit):
            # Segment once more: each point to the surface that explains it better; the second
            # surface refitted on its own points only (the first pass's set holds some of the
            # first surface where the two meet).
            res2 = _residual_m(second, every, bw)
            mine = (np.abs(res2) < np.abs(res)) & (np.abs(res2) < qc.second_surface_sigmas * noise)
            n_mine = int(np.count_nonzero(mine))
            if n_mine >= qc.min_points:
                step = max(1, n_mine // qc.max_points)
                again = _fit_surface(
                    every[mine][::step],
                    d2_every[mine][::step],
                    camera_axis,
                    qc,
                    with_leverage=False,
                )
                if isinstance(again, _Fit):
                    again = _tighten(again, noise, camera_axis, qc)
                if isinstance(again, _Fit):
                    second = again
    # The bar is the first surface's own share where that is lower: the scale both are held to
    # comes from a few thinned points and can be under the sensor's noise (0.5 mm against 1.7 at
    # 0.75 m), and then a finger lying on the chest, a cylinder of 12 mm, explains 42-63 % of
    # its points where the chest explains 31-41 % of its own; held to 70 % it was outliers and
    # the chest answered, 3.4-4.5 mm too far. Taking the second surface moves this fit's answer
    # nearer, never farther (the farther of the two never answers): the lower bar errs safe.
    if not isinstance(second, _Fit) or second.inliers < min(_MIN_SECOND_INLIERS, fit.inliers):
        # Nearer points that make no surface of their own: the first surface stands, and the
        # answer is held no farther than those of them that lie together (not stray pixels).
        note = f"{n_closer} points nearer than the surface fit no surface of their own"
        return fit, 1, note, True, every[closer]
    dist2 = float(np.sqrt(second.origin @ second.origin))
    note = f"nearer of two surfaces (the other {abs(dist1 - dist2):.4f} m farther)"
    return (second, 2, note, True, _NONE) if dist2 < dist1 else (fit, 2, note, True, _NONE)


#: No nearer points that make no surface (:attr:`_Answer.unmodelled`).
_NONE = np.empty((0, 3))
_NONE.flags.writeable = False
#: A nearer point stands for a surface where at least this many other nearer points lie within
_NEARER_SUPPORT_POINTS = 3
#: this distance (m) of it; a point with fewer is stray (a flying pixel, an outlier).
_NEARER_SUPPORT_M = 0.007


def _unmodelled_nearer_m(closer: FloatArray, qc: QuadricConfig) -> float:
    """Distance (m) from the HIP within which nearer points that make no surface of their own
    (``closer``, HIP-relative) stand for a surface; ``inf`` if they stand for none.

    Too many to be stray noise and too few or too scattered to model (the flank of a finger
    lying on the chest, seen edge-on: 29-67 points, the chest 4 mm farther): what is not
    modelled is not free space, so the answer is held no farther than the distance within
    which ``second_surface_min_points`` of them lie (:func:`_held_no_farther`). Only points
    with neighbours among them count: outliers scattered over the patch (flying pixels) stand
    for no surface."""
    k = qc.second_surface_min_points
    if len(closer) < k:
        return math.inf
    d2_closer = np.einsum("ij,ij->i", closer, closer)
    keep = max(qc.max_points, k)
    if len(closer) > keep:
        # The nearest ones decide, and a k-d tree of thousands costs milliseconds (5000: 6.6).
        nearest = np.argpartition(d2_closer, keep - 1)[:keep]
        closer, d2_closer = closer[nearest], d2_closer[nearest]
    neighbours = cKDTree(closer).query_ball_point(closer, _NEARER_SUPPORT_M, return_length=True)
    supported = d2_closer[neighbours - 1 >= _NEARER_SUPPORT_POINTS]  # itself counted
    if len(supported) < k:
        return math.inf
    return float(np.sqrt(np.partition(supported, k - 1)[k - 1]))


def _held_no_farther(estimate: SurfaceFit, unmodelled_m: float, hip: FloatArray) -> SurfaceFit:
    """``estimate`` moved along its normal to ``unmodelled_m`` from the HIP where it is farther
    (:func:`_unmodelled_nearer_m`, worked out once, for the answer that won). Never farther.
    Applied to the final answer, so that the choice between fits (the nearest patch's, the one
    across a hole) is made as before and keeps its normal."""
    excess = estimate.d_proj(hip, 0.0) - unmodelled_m
    if not excess > 0.0:
        return estimate
    note = f"held {excess * 1e3:.1f} mm nearer, to nearer points that make no surface"
    return _moved_nearer(estimate, excess, note)


#: Radius (m) of the patch whose plane residuals measure the noise,
_NOISE_PATCH_M = 0.007
#: around the centroid of this many points nearest the HIP.
_NOISE_SEED_POINTS = 24


def _patch_noise(rel: FloatArray, d2: FloatArray, qc: QuadricConfig) -> float:
    """Noise scale (m) of the surface nearest the HIP: residuals of a plane through the points
    within ``_NOISE_PATCH_M`` of the centroid of the ``_NOISE_SEED_POINTS`` nearest ones. Small
    enough a patch to hold one surface even at a crease, where a fit's residuals mix two.

    Centred on those points' centroid, not on the nearest point: the nearest point is the one
    the noise moved farthest toward the HIP, and a ball around it holds only points moved about
    as far, a thin slice of the noise, which then lets noise pass for a second, nearer surface.
    Measured on the held-out far bodies (1.2-1.45 m, 2-5 mm of depth noise; ``bench
    perception``): |d_proj err| p90 3.17 -> 0.78 mm; where the ball holds too few points to
    measure (a far body's lie 3.6 mm apart) the noise floor stands, as before."""
    m = min(len(rel), _NOISE_SEED_POINTS)
    seed = rel[np.argpartition(d2, m - 1)[:m]].mean(axis=0)
    off = rel - seed
    patch = rel[np.einsum("ij,ij->i", off, off) < _NOISE_PATCH_M * _NOISE_PATCH_M]
    if len(patch) < 6:
        return qc.noise_floor_m
    centred = patch - patch.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    return _robust_scale(centred @ normal, qc.noise_floor_m)


def _initial_plane(pts: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """Centroid and unit normal (either sign) of the points by SVD; None if they are collinear."""
    if len(pts) < 3:
        return None
    centroid = pts.mean(axis=0)
    _, sv, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    if not sv[1] > RANK_TOL * sv[0]:
        return None
    return centroid, vt[2]


def _refit(
    pts: FloatArray,
    robust: FloatArray,
    origin: FloatArray,
    normal: FloatArray,
    models: tuple[str, ...],
    qc: QuadricConfig,
    with_leverage: bool = True,
) -> tuple[FloatArray, FloatArray, str, FloatArray, FloatArray, float] | str:
    """One weighted fit in the frame at ``origin``; its closest point to the HIP (at 0).

    Returns ``(closest, normal, model, frame, coef, leverage)`` or a string saying what failed;
    ``leverage`` (``with_leverage``, else inf): the standard error of the fitted height at the
    closest point per unit residual scale
    (:meth:`~hapticloud.core.geometry.quadric.NestedQuadricLSQ.leverage`).
    """
    bw = qc.bandwidth_m
    frame = frame_from_unit_normal(normal)
    local = ((pts - origin) @ frame) * (1.0 / bw)
    r2 = np.einsum("ij,ij->i", local, local)
    sel = np.flatnonzero(r2 < _SUPPORT_SIGMAS**2)
    w = np.exp(-0.5 * r2[sel]) * robust[sel]
    if int(np.count_nonzero(w > 1e-3)) < qc.min_points:
        return f"{int(np.count_nonzero(w > 1e-3))} points near the surface"
    q = local[sel]
    k_max = max(len(QUADRIC_MODELS[m]) for m in models)
    lsq = NestedQuadricLSQ(q, w, min(k_max, 6))
    coef6 = None
    if k_max > 6:
        # The z-terms use a prediction of z, not the measured z: with z on both sides the fit
        # explains noise with itself (errors in variables; on flat data a pair of planes).
        coef6, _ = lsq.solve("paraboloid")
        if coef6 is not None:
            lsq = NestedQuadricLSQ(q, w, k_max, paraboloid_height(q, coef6))
    h_local = -(origin @ frame) / bw
    failure = "ill-conditioned surface fit"
    for model in _ranked_models(lsq, w, models, qc):
        coef, _ = lsq.solve(model)
        if coef is None:
            continue
        if len(QUADRIC_MODELS[model]) > 6:
            coef = refine_quadric_heights(q, w, coef, model, qc.shape_iterations)
        found = local_quadric_closest(coef, h_local)
        if found is None:
            failure = "no closest point on the fit"
            continue
        q_star, n_star = found
        if not n_star[2] > _MIN_NORMAL_COS:
            failure = "closest point on a far sheet of the fit"
            continue
        z_terms = len(QUADRIC_MODELS[model]) > 6
        if z_terms and not _one_sheet(q, coef, q_star):
            # The z-terms chased noise: a second sheet or a hole where the data are silent.
            failure = f"{model} fit folds near the closest point"
            continue
        leverage = math.inf
        if with_leverage:  # only the answer's: the frame-moving refits discard theirs
            zhat = (
                float(paraboloid_height(q_star[None, :], coef6)[0])
                if z_terms and coef6 is not None
                else None
            )
            leverage = lsq.leverage(model, q_star, zhat)
        return origin + bw * (frame @ q_star), frame @ n_star, model, frame, coef, leverage
    return failure


def _ranked_models(
    lsq: NestedQuadricLSQ, w: FloatArray, models: tuple[str, ...], qc: QuadricConfig
) -> list[str]:
    """``models`` by increasing BIC: the simplest model that explains the data comes first.

    A single (forced) model is followed by the simpler ones, in case the data cannot carry it
    (a plane has no curvature to fit).
    """
    if len(models) == 1:
        return list(reversed(_MODEL_ORDER[: _MODEL_ORDER.index(models[0]) + 1]))
    wsum = float(w.sum())
    n_eff = wsum * wsum / float(w @ w)
    log_n = math.log(max(n_eff, 2.0))
    scores = []
    for i, m in enumerate(models):
        rss = lsq.rss(m)
        if np.isfinite(rss):
            fit_term = n_eff * math.log(max(rss / wsum, 1e-300))
            scores.append((fit_term + qc.bic_penalty * len(QUADRIC_MODELS[m]) * log_n, i, m))
    return [m for _, _, m in sorted(scores)]


def _one_sheet(q: FloatArray, coef: FloatArray, q_star: FloatArray) -> bool:
    """True when a spheroid/quadric fit is one smooth height field around the closest point.

    ``D = -dF/dz = 1 - 2 czz z - cxz x - cyz y`` is 1 at the origin and falls to 0 where the
    surface turns vertical. Between the closest point and the data nearest to it (the hidden
    disc, where no point holds the fit) a body surface stays a gentle height field; z-terms
    fitted to noise instead fold the surface there or open a hole in it (no real height).
    Probed at the closest point and on two rings reaching out to the nearest point. (The data
    themselves may legitimately reach a silhouette, D = 0: they are not probed.)
    """
    gap = float(np.sqrt(np.min((q[:, 0] - q_star[0]) ** 2 + (q[:, 1] - q_star[1]) ** 2)))
    probe = q_star[:2] + gap * _PROBE_RING
    return not _heights_folded(np.column_stack((probe, np.zeros(len(probe)))), coef).any()


def _heights_folded(q: FloatArray, coef: FloatArray) -> FloatArray:
    """Where the vertical through ``(x, y)`` misses the surface or meets it nearly edge-on."""
    lin = 1.0 - coef[7] * q[:, 0] - coef[8] * q[:, 1]
    p = paraboloid_height(q, coef)
    disc = lin * lin - 4.0 * coef[6] * p
    height = quadric_height(q, coef)
    den = lin - 2.0 * coef[6] * height
    return (disc < 0.0) | (den < _MIN_SHEET_DEN)


def _surround(offsets: FloatArray, normal: FloatArray, bw: float) -> float:
    """1 when the points surround the closest point, falling to 0 as they sit to one side of it.

    From the widest empty angular sector (36 bins of 10°) around the normal within two
    bandwidths: up to a quarter turn (a silhouette nearby) counts as surrounded, half a turn
    (the closest point on the edge of the data) scores 2/3, a full turn 0.
    """
    close = offsets[np.einsum("ij,ij->i", offsets, offsets) < (2.0 * bw) ** 2]
    if len(close) < 3:
        return 0.0
    tangent = close @ frame_from_unit_normal(normal)[:, :2]
    bins = (np.arctan2(tangent[:, 1], tangent[:, 0]) + np.pi) * (_SECTORS / (2.0 * np.pi))
    filled = np.bincount(np.minimum(bins.astype(np.int64), _SECTORS - 1), minlength=_SECTORS) > 0
    if filled.all():
        return 1.0
    # Longest circular run of empty sectors.
    empty = np.concatenate((~filled, ~filled)).astype(np.int8)
    edges = np.flatnonzero(np.diff(np.concatenate(([0], empty, [0]))))
    widest = min(int((edges[1::2] - edges[::2]).max()), _SECTORS)
    return float(np.clip((_SECTORS - widest) / (0.75 * _SECTORS), 0.0, 1.0))

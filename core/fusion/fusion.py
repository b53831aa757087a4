"""SurfaceFusion: noisy 30 Hz per-camera estimates in, a smooth surface at any sample time out.

``add`` keeps the valid estimates of every camera in a sliding window; ``sample(t)`` refits the
window only when an estimate arrived since the last fit (the polynomial is cached, evaluating it is
a few float operations), evaluates it at ``t`` (extrapolating at most ``max_extrapolation_s`` past
the newest estimate, then holding), and moves the PID followers one tick toward that target.

Staleness: with no valid estimate for ``max_age_s`` the output is invalid and stale and the
followers forget their state; an estimate arriving after such a gap also drops the pre-gap
window, so the output restarts from the new data without a jump toward the old state.

Several cameras (:class:`CameraAgreement`): with two or more cameras in the window each is also
fitted on its own. Their distances from the HIP to their own surfaces are compared: a camera
farther than the nearest by more than their scatter explains (a calibration error between the
cameras, a camera that sees another body at a crease) is left out of the fit, so the nearer
surface answers, never the farther (the safe side); the cameras that agree are fitted together,
weighted by the inverse square of the residual their surface fits measured (a far, noisy camera
weighs less). One camera in the window: the fit is exactly the single-camera one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..perception.estimate import SurfaceEstimate
from ..validation import as_finite_scalar
from .config import FusionConfig
from .follower import NormalFollower, PidGains, PointFollower
from .regression import (
    PolyFit,
    Vec3,
    age_weights,
    count_distinct_times,
    fit_weighted,
    fit_window,
    newest_index,
)

FloatArray = NDArray[np.float64]

_ZERO: Vec3 = (0.0, 0.0, 0.0)
_UP: Vec3 = (0.0, 0.0, 1.0)
_NO_HIP = (math.nan, math.nan, math.nan)


@dataclass(frozen=True, slots=True)
class CameraAgreement:
    """How the cameras in the window agree (empty with fewer than two cameras).

    ``distances_m`` holds how much farther each camera puts the surface than the nearest camera
    (m, along the newest normal: one motion fitted to all, one offset per camera);
    ``scatter_m`` the scatter of its estimates about that fit (m, the noise that explains a
    difference); ``residual_m`` the median
    surface-fit residual its estimates reported (m, 0 if unknown) and ``weights`` the share each
    has in the fit. ``disagreement_m`` is the largest minus the smallest distance, ``limit_m``
    what their scatter explains between those two; ``disagree`` is True when a camera was left
    out for it (``dropped``), and ``note`` says it in words.
    """

    cameras: tuple[str, ...] = ()
    distances_m: tuple[float, ...] = ()
    scatter_m: tuple[float, ...] = ()
    residual_m: tuple[float, ...] = ()
    weights: tuple[float, ...] = ()
    disagreement_m: float = 0.0
    limit_m: float = 0.0
    disagree: bool = False
    dropped: tuple[str, ...] = ()
    note: str = ""


_ONE_CAMERA = CameraAgreement()


def _median(values: list[float]) -> float:
    """``np.median`` of a non-empty list of finite floats, bit for bit (the mean of the two
    middle values is their sum over 2), without its array overhead."""
    ordered = sorted(values)
    half = len(ordered) // 2
    if len(ordered) % 2:
        return ordered[half]
    return (ordered[half - 1] + ordered[half]) / 2


@dataclass(frozen=True, slots=True)
class FusedSurface:
    """The fused surface at sample time ``t`` (s).

    ``centroid`` (m) and unit ``normal`` (out of the surface toward the HIP) are the follower's
    output; ``target_centroid`` / ``target_normal`` the regression's value before the follower
    (the paper's Fig. 8 "planned trajectory"); ``velocity`` (m/s) the regression's derivative at
    ``t`` (zero while holding). All vectors are finite read-only ``(3,)`` arrays; when ``valid`` is
    False they are the last values held (or placeholders) and ``reason`` says why; a valid result
    has ``reason`` empty or starting with ``"holding"``. ``age_s`` is the time since the newest
    valid estimate (s, ``inf`` before any), ``n_samples`` / ``degree`` (of the centroid) /
    ``cameras`` describe the fit, ``seq`` counts the results produced. ``free_m`` > 0 is a
    camera's fresh proof (no older than ``max_age_s``) that no surface lies within that distance
    of ``free_hip`` (a frame that saw its whole workspace empty); 0 without one.

    The fused quality, with two or more cameras: ``disagreement_m`` is how far apart (m, along
    the HIP's distance) the cameras' own surfaces lie, ``disagree`` is True when that is more
    than their noise explains (the farther camera is then left out: the nearer surface answers)
    and ``quality_note`` says it in words (and the cameras' weights); ``agreement`` holds the
    figures per camera. 0, False, "" and empty with one camera.
    """

    t: float
    centroid: FloatArray
    normal: FloatArray
    valid: bool
    velocity: FloatArray
    target_centroid: FloatArray
    target_normal: FloatArray
    age_s: float
    stale: bool
    reason: str
    n_samples: int
    degree: int
    cameras: tuple[str, ...]
    seq: int
    free_m: float = 0.0
    free_hip: FloatArray | None = None
    disagreement_m: float = 0.0
    disagree: bool = False
    quality_note: str = ""
    agreement: CameraAgreement = _ONE_CAMERA


class SurfaceFusion:
    """Merges estimates of all cameras and up-samples them to the control rate.

    Parameters
    ----------
    config
        Window, weights, follower gains, limits (defaults: :class:`FusionConfig`).

    Examples
    --------
    >>> from hapticloud.core.perception.estimate import SurfaceEstimate
    >>> fusion = SurfaceFusion(FusionConfig())
    >>> fusion.add(SurfaceEstimate(0.0, "cam0", (0.1, 0.0, 0.5), (0.0, 0.0, 1.0), True))
    True
    >>> fused = fusion.sample(0.01)
    >>> fused.valid, fused.centroid.tolist(), fused.normal.tolist()
    (True, [0.1, 0.0, 0.5], [0.0, 0.0, 1.0])
    """

    def __init__(self, config: FusionConfig | None = None) -> None:
        cfg = FusionConfig() if config is None else config
        if not isinstance(cfg, FusionConfig):
            raise InputError(f"config: expected a FusionConfig, got {type(cfg).__name__}")
        self._cfg = cfg
        self._point = PointFollower(PidGains.make(cfg.kp, cfg.ki, cfg.kd, cfg.i_accel_limit_m_s2))
        self._normal = NormalFollower(
            PidGains.make(
                cfg.normal_kp, cfg.normal_ki, cfg.normal_kd, cfg.normal_i_accel_limit_rad_s2
            )
        )
        self.n_added = 0
        self.n_invalid = 0
        self.n_late = 0
        self.reset()

    @property
    def config(self) -> FusionConfig:
        return self._cfg

    @property
    def fit(self) -> PolyFit | None:
        """The current window's polynomials (see :meth:`prepare`), ``None`` with no data."""
        return self.prepare()

    def prepare(self) -> PolyFit | None:
        """Refit now if an estimate arrived since the last fit; returns the current fit.

        :meth:`sample` does this lazily; a caller that adds estimates outside the control tick
        can call it right after :meth:`add` so the tick only evaluates the cached polynomials.
        """
        self._refit()
        return self._fit

    @property
    def last(self) -> FusedSurface | None:
        """The most recent result of :meth:`sample`."""
        return self._last

    def reset(self) -> None:
        """Forget all estimates and the followers' state (counters are kept)."""
        # (t, cx, cy, cz, nx, ny, nz, residual_m, hx, hy, hz) per estimate; hip NaN if unknown.
        self._rows: list[tuple[float, ...]] = []
        self._cam: list[str] = []
        self._newest = -math.inf
        self._dirty = False
        self._fit: PolyFit | None = None
        self._agreement = _ONE_CAMERA
        self._fit_id = 0
        self._prev_eval: tuple[int, float, Vec3, Vec3] | None = None
        self._t_prev = -math.inf
        self._last: FusedSurface | None = None
        self._hold: tuple[Vec3, Vec3] | None = None
        self._held_eval: tuple[PolyFit, float, Vec3, Vec3] | None = None
        self._emitted: tuple[tuple[Vec3, ...], tuple[FloatArray, ...]] | None = None
        self._last_fit_id = -1
        self._seq = 0
        self._free: tuple[float, FloatArray, float] | None = None  # (t, hip, radius m)
        self._point.reset()
        self._normal.reset()

    # ----- input -----------------------------------------------------------------------------
    def add(self, est: SurfaceEstimate) -> bool:
        """Take one estimate of any camera; returns True if it entered the window.

        Invalid estimates and non-finite times are counted in ``n_invalid``, estimates older than
        the window in ``n_late``; neither is used.
        """
        if not isinstance(est, SurfaceEstimate):
            raise InputError(f"est: expected a SurfaceEstimate, got {type(est).__name__}")
        self.n_added += 1
        t = est.t
        if not est.valid or not math.isfinite(t):
            self.n_invalid += 1
            if est.free_m > 0.0 and est.hip is not None and math.isfinite(t):
                if self._free is None or t >= self._free[0]:
                    self._free = (t, est.hip, est.free_m)
            return False
        cfg = self._cfg
        if t > self._newest + cfg.max_age_s and self._rows:
            # After a stale gap the old window describes a surface that has since moved.
            self._drop_all()
        elif t <= self._newest - cfg.window_s:
            self.n_late += 1
            return False
        hip = _NO_HIP if est.hip is None else est.hip.tolist()
        self._rows.append((t, *est.centroid.tolist(), *est.normal.tolist(), est.residual_m, *hip))
        self._cam.append(est.camera)
        if t > self._newest:
            self._newest = t
        self._dirty = True
        return True

    def _drop_all(self) -> None:
        self._rows, self._cam = [], []
        self._point.reset()
        self._normal.reset()

    def _refit(self) -> None:
        if not self._dirty:
            return
        self._dirty = False
        cfg = self._cfg
        rows = np.array(self._rows)
        times = rows[:, 0]
        keep = np.flatnonzero(times > self._newest - cfg.window_s)  # edge weight is 0
        if keep.size > cfg.max_samples:
            # Newest first by time (stable, so the order of arrival breaks ties deterministically).
            keep = np.sort(keep[np.argsort(-times[keep], kind="stable")[: cfg.max_samples]])
        if keep.size < times.size:
            idx = keep.tolist()
            self._rows = [self._rows[i] for i in idx]
            self._cam = [self._cam[i] for i in idx]
            rows = rows[keep]
        self._agreement = _ONE_CAMERA
        fit = None
        if cfg.weigh_cameras and len(set(self._cam)) > 1:
            fit = self._fit_cameras(rows)
        self._fit = self._fit_rows(rows, self._cam) if fit is None else fit
        self._fit_id += 1

    def _fit_rows(
        self, rows: FloatArray, cams: list[str], weights: FloatArray | None = None
    ) -> PolyFit:
        cfg = self._cfg
        return fit_window(
            rows[:, 0],
            rows[:, 1:4],
            rows[:, 4:7],
            cams,
            window_s=cfg.window_s,
            half_life_s=cfg.weight_half_life_s,
            weighting=cfg.weighting,
            max_degree=cfg.max_degree,
            normal_max_degree=cfg.normal_max_degree,
            time_resolution_s=cfg.time_resolution_s,
            sample_weights=weights,
        )

    def _fit_cameras(self, rows: FloatArray) -> PolyFit | None:
        """The cameras compared, weighted, and the fit of those that agree with the nearest
        (see the module docstring); ``None`` when they cannot be told apart (too few samples).

        This runs in the control loop's slack (:meth:`prepare` after the torque is sent): what
        needs no array is done on the rows' Python floats, and every figure that reaches the
        result is computed by the same operations in the same order as the plain NumPy version
        it replaced (the fused output did not change by one bit).
        """
        cfg = self._cfg
        cams = self._cam
        table = self._rows
        names = sorted(set(cams))
        k = len(names)
        cam_index = {name: i for i, name in enumerate(names)}
        which_list = [cam_index[c] for c in cams]
        counts = [0] * k
        newest_of = [-math.inf] * k
        known: list[list[float]] = [[] for _ in range(k)]  # the residuals reported (> 0)
        for i, row in zip(which_list, table, strict=True):
            counts[i] += 1
            if row[0] > newest_of[i]:
                newest_of[i] = row[0]
            if row[7] > 0.0:
                known[i].append(row[7])
        # Only cameras with a recent estimate are compared: a camera that stopped seeing the
        # surface has old rows that weigh little, and it must not answer alone (stale fit).
        t_newest = max(newest_of)
        fresh_list = [t_newest - t <= cfg.max_extrapolation_s for t in newest_of]
        if sum(fresh_list) < 2:
            return None  # before any array is built: nothing to compare
        times = rows[:, 0]
        n = len(times)
        newest = newest_index(times)
        which = np.array(which_list)
        # One motion for all, one offset per camera: the centroids' height along the newest
        # normal, y = p(tau) + offset[camera]. Each camera's own fit would compare a camera that
        # has one recent sample (a constant) with another's moving fit: motion, not disagreement.
        y = rows[:, 1:4] @ rows[newest, 4:7]
        age = times[newest] - times
        w = age_weights(age, cfg.weight_half_life_s, cfg.window_s, cfg.weighting)
        n_times = count_distinct_times(times, cfg.time_resolution_s)
        degree = min(cfg.max_degree, n_times - 1)
        design = np.zeros((n, degree + k))
        design[:, :k] = np.eye(k)[which]  # offsets replace the constant term
        if degree > 0:
            tau = -age / cfg.window_s
            design[:, k] = tau
            for j in range(2, degree + 1):
                design[:, k + j - 1] = tau**j
        sw = np.sqrt(w)
        coef, _, rank, sv = np.linalg.lstsq(design * sw[:, None], y * sw, rcond=None)
        if rank < design.shape[1] or n - design.shape[1] < 1 or not sv[-1] > 1e-9 * sv[0]:
            return None
        resid = y - design @ coef
        scatter = np.zeros(k)
        for i in range(k):
            n_mine = counts[i]
            # The camera's share of the lost degrees of freedom (its offset, a share of p's).
            dof = n_mine - 1 - degree * n_mine / n
            if dof > 0.0:
                mine = which == i
                wi, ri = w[mine], resid[mine]
                scatter[i] = math.sqrt(float(wi @ (ri * ri)) / float(wi.sum()) * n_mine / dof)
        # A camera whose surface is higher along the normal (toward the HIP) is nearer.
        fresh = np.array(fresh_list)
        dist_a = -coef[:k]
        dist_a = dist_a - dist_a[fresh].min()
        dist = dist_a.tolist()
        fresh_idx = [i for i in range(k) if fresh_list[i]]
        # The first of equals, like argmin / argmax (the distances are finite).
        near = min(fresh_idx, key=dist.__getitem__)
        far = max(fresh_idx, key=dist.__getitem__)
        limits = np.maximum(
            cfg.disagreement_min_m, cfg.disagreement_sigmas * np.hypot(scatter, scatter[near])
        ).tolist()
        agree = [dist[i] <= limits[i] or not fresh_list[i] for i in range(k)]
        residual = [_median(values) if values else 0.0 for values in known]
        floor = cfg.residual_floor_m
        if all(r > 0.0 for r in residual):
            # (floor / max(r, floor))²: a product, as NumPy squares (no pow()).
            ratios = [floor / (r if r >= floor else floor) for r in residual]
            w_cam = [q * q for q in ratios]
        else:  # a camera that does not report its residual: no basis to weigh them apart
            w_cam = [1.0] * k
        keep = [i for i in range(k) if agree[i]]
        w_kept = np.array([w_cam[i] for i in keep])
        w_keep = (w_kept / w_kept.sum()).tolist()  # NumPy's summation order kept
        dropped = tuple(names[i] for i in range(k) if not agree[i])
        spread = dist[far]
        if dropped:
            note = (
                f"cameras disagree by {spread * 1e3:.1f} mm (noise explains "
                f"{limits[far] * 1e3:.1f} mm): the nearer surface ({names[near]}) answers, "
                f"{', '.join(dropped)} left out"
            )
        else:
            note = "weights " + ", ".join(
                f"{names[i]} {wk:.2f}" for i, wk in zip(keep, w_keep, strict=True)
            )
        weights = [0.0] * k
        for i, wk in zip(keep, w_keep, strict=True):
            weights[i] = wk
        self._agreement = CameraAgreement(
            tuple(names),
            tuple(dist),
            tuple(scatter.tolist()),
            tuple(residual),
            tuple(weights),
            spread,
            limits[far],
            bool(dropped),
            dropped,
            note,
        )
        if dropped:
            idx = np.flatnonzero(np.array(agree)[which])
            return self._fit_rows(
                rows[idx], [cams[i] for i in idx.tolist()], np.array(w_cam)[which[idx]]
            )
        if w_cam.count(w_cam[0]) == k:
            return None  # all agree, equal trust: the plain fit of every row
        # Every row, so the window's age weights and distinct times computed above serve.
        return fit_weighted(
            times,
            rows[:, 1:4],
            rows[:, 4:7],
            cams,
            newest,
            w * np.array(w_cam)[which],
            n_times,
            window_s=cfg.window_s,
            max_degree=cfg.max_degree,
            normal_max_degree=cfg.normal_max_degree,
        )

    # ----- output ----------------------------------------------------------------------------
    def sample(self, t: float) -> FusedSurface:
        """The fused surface at time ``t`` (s), advancing the followers by ``t - previous t``.

        A ``t`` not after the previous sample time does not advance the followers (the result is
        reported at the previous time); a gap longer than ``reset_dt_s`` restarts them at the
        target.
        """
        t = t if type(t) is float and math.isfinite(t) else as_finite_scalar(t, "t")
        self._refit()
        advance = t > self._t_prev
        if not advance:
            if self._last is not None and self._last_fit_id == self._fit_id:
                return self._last
            t = self._t_prev if self._t_prev > -math.inf else t
        t_prev = self._t_prev
        dt = t - t_prev
        self._t_prev = t
        fit = self._fit
        cfg = self._cfg
        if fit is None:
            return self._emit(
                t,
                _ZERO,
                _UP,
                _ZERO,
                _UP,
                _ZERO,
                False,
                False,
                "no valid estimate yet",
                math.inf,
                None,
            )
        age = t - fit.t_ref
        if not fit.valid:
            self._point.reset()
            self._normal.reset()
            return self._emit(t, *self._held(fit, t), _ZERO, False, False, fit.reason, age, fit)
        if age > cfg.max_age_s:
            held = self._held(fit, t)
            self._point.reset()
            self._normal.reset()
            reason = f"stale: no valid estimate for {age:.3f} s (max_age_s {cfg.max_age_s})"
            return self._emit(t, *held, _ZERO, False, True, reason, age, fit)
        horizon = fit.t_ref + cfg.max_extrapolation_s
        t_eval = t if t < horizon else horizon
        tc, tn, vel = fit.evaluate(t_eval)
        reason = ""
        if t > horizon:
            vel = _ZERO
            reason = f"holding: newest estimate {age:.3f} s old (max_extrapolation_s reached)"
        point, normal = self._point, self._normal
        if not point.initialised or dt > cfg.reset_dt_s:
            point.reset(tc)
            normal.reset(tn)
            yc, yn = tc, tn
        elif advance:
            yc, yn = self._follow(fit, t_eval, min(t_prev, horizon), tc, tn, dt)
        else:
            yc, yn = tuple(point.y), normal.n
        self._prev_eval = (self._fit_id, t_eval, tc, tn)
        return self._emit(t, yc, yn, tc, tn, vel, True, False, reason, age, fit)

    def _follow(
        self, fit: PolyFit, t_eval: float, t_eval_prev: float, tc: Vec3, tn: Vec3, dt: float
    ) -> tuple[Vec3, Vec3]:
        cfg = self._cfg
        ff = cfg.feedforward
        ffc: Vec3 = _ZERO
        pn: Vec3 | None = None
        if ff > 0.0:
            prev = self._prev_eval
            if prev is not None and prev[0] == self._fit_id and prev[1] == t_eval_prev:
                pc, pn = prev[2], prev[3]
            else:
                # The target moved along this polynomial since the previous tick; re-evaluating
                # it there keeps a refit's jump out of the feed-forward (the PID smooths that).
                pc, pn, _ = fit.evaluate(t_eval_prev)
            ffc = (ff * (tc[0] - pc[0]), ff * (tc[1] - pc[1]), ff * (tc[2] - pc[2]))
        yc = self._point.step(tc, dt, ffc, cfg.max_speed_m_s * dt)
        yn = self._normal.step(tn, dt, pn, ff, cfg.max_normal_rate_rad_s * dt)
        return yc, yn

    def _held(self, fit: PolyFit, t: float) -> tuple[Vec3, Vec3, Vec3, Vec3]:
        """Output and target shown while invalid: the last output if any, the held fit value."""
        t_eval = min(t, fit.t_ref + self._cfg.max_extrapolation_s)
        cached = self._held_eval
        if cached is not None and cached[0] is fit and cached[1] == t_eval:
            # Stale for many ticks on end: the same fit at the same (capped) time.
            tc, tn = cached[2], cached[3]
        else:
            tc, tn, _ = fit.evaluate(t_eval)
            self._held_eval = (fit, t_eval, tc, tn)
        if self._hold is not None:
            return self._hold[0], self._hold[1], tc, tn
        return tc, tn, tc, tn

    def _emit(
        self,
        t: float,
        yc: Vec3,
        yn: Vec3,
        tc: Vec3,
        tn: Vec3,
        vel: Vec3,
        valid: bool,
        stale: bool,
        reason: str,
        age: float,
        fit: PolyFit | None,
    ) -> FusedSurface:
        self._seq += 1
        self._last_fit_id = self._fit_id
        if valid:
            self._hold = (yc, yn)
        vectors = (yc, yn, vel, tc, tn)
        last = self._emitted
        if (
            last is not None
            and last[0][0] is yc
            and last[0][1] is yn
            and last[0][2] is vel
            and last[0][3] is tc
            and last[0][4] is tn
        ):
            # The very same tuples as last tick (holding, stale): their read-only arrays serve.
            arrays = last[1]
        else:
            # One read-only (5, 3) array and five row views: the same values as five separate
            # read-only arrays, at a fifth of the calls (this runs every control tick).
            rows = np.array(vectors, dtype=np.float64)
            rows.setflags(write=False)
            arrays = (rows[0], rows[1], rows[2], rows[3], rows[4])
            self._emitted = (vectors, arrays)
        centroid, normal, velocity, target_centroid, target_normal = arrays
        agreement = _ONE_CAMERA if fit is None else self._agreement
        free = self._free
        if free is not None and not t - free[0] <= self._cfg.max_age_s:
            free = None
        out = FusedSurface(
            t,
            centroid,
            normal,
            valid,
            velocity,
            target_centroid,
            target_normal,
            max(age, 0.0),
            stale,
            reason,
            0 if fit is None else fit.n_samples,
            0 if fit is None else fit.degree,
            () if fit is None else fit.cameras,
            self._seq,
            0.0 if free is None else free[2],
            None if free is None else free[1],
            agreement.disagreement_m,
            agreement.disagree,
            agreement.note,
            agreement,
        )
        self._last = out
        return out

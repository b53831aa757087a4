"""A D435-like depth noise model applied to an ideal depth image.

Applied in this order, each step independent per pixel (the D435's spatially correlated stereo
noise is not modelled):

1. *flying pixels*: a pixel whose 4-neighbourhood spans a depth step larger than ``edge_jump_m``
   takes, with probability ``flying_pixel_probability``, a depth drawn uniformly between the
   nearest (foreground) and farthest (background) depth of that neighbourhood;
2. *depth noise*: ``z += N(0, sigma(z))`` with ``sigma(z) = sigma_base_m + sigma_z2_m_per_m2 z^2``
   (stereo error grows with z^2). ``sigma`` is the std of the depth value; since the pixel stays put
   the 3D point moves along its ray;
3. *quantisation* of z to ``quantisation_m`` (the D435's 1 mm depth unit);
4. *dropouts*: a valid pixel returns 0 with probability ``dropout_fraction``, plus up to
   ``grazing_dropout`` more as the incidence angle goes from ``grazing_start_deg`` to 90 deg
   (linear in the cosine);
5. depths outside ``[min_depth_m, max_depth_m]`` return 0.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Self

import numpy as np
from numpy.typing import NDArray

from ..config import StageConfig, param
from ..errors import ConfigError

Depth = NDArray[np.float32]


@dataclass(frozen=True)
class DepthNoiseConfig(StageConfig):
    """Noise of the simulated depth camera (defaults: a D435 at 848x480)."""

    sigma_base_m: float = param(
        0.0005, lo=0.0, hi=0.05, unit="m", doc="depth noise std at zero depth"
    )
    sigma_z2_m_per_m2: float = param(
        0.002, lo=0.0, hi=0.05, unit="1/m", doc="growth of the depth noise std with depth squared"
    )
    quantisation_m: float = param(
        0.001, lo=0.0, hi=0.01, unit="m", doc="depth step (the D435 depth unit); 0 turns it off"
    )
    dropout_fraction: float = param(
        0.02, lo=0.0, hi=1.0, doc="probability that a pixel returns no depth"
    )
    grazing_start_deg: float = param(
        65.0, lo=0.0, hi=90.0, unit="deg", doc="incidence angle where dropouts start to rise"
    )
    grazing_dropout: float = param(
        0.5, lo=0.0, hi=1.0, doc="extra dropout probability reached at 90 deg incidence"
    )
    flying_pixel_probability: float = param(
        0.3, lo=0.0, hi=1.0, doc="probability that a pixel at a depth edge flies"
    )
    edge_jump_m: float = param(
        0.03, lo=0.001, hi=2.0, unit="m", doc="neighbour depth step that counts as a depth edge"
    )
    min_depth_m: float = param(0.2, lo=0.0, hi=2.0, unit="m", doc="nearest valid depth")
    max_depth_m: float = param(4.0, lo=0.1, hi=20.0, unit="m", doc="farthest valid depth")
    seed: int = param(0, lo=0, hi=2**31 - 1, doc="random seed (with camera name and time)")

    def check(self) -> None:
        if self.min_depth_m >= self.max_depth_m:
            raise ConfigError(
                f"min_depth_m = {self.min_depth_m}, max_depth_m = {self.max_depth_m}: "
                "min_depth_m must be below max_depth_m"
            )

    @classmethod
    def noiseless(cls, **overrides: float) -> Self:
        """No noise, no quantisation, no dropouts, no flying pixels (range limits kept)."""
        values: dict[str, float] = dict(
            sigma_base_m=0.0,
            sigma_z2_m_per_m2=0.0,
            quantisation_m=0.0,
            dropout_fraction=0.0,
            grazing_dropout=0.0,
            flying_pixel_probability=0.0,
        )
        values.update(overrides)
        return cls(**values)

    def sigma_m(self, depth_m: NDArray | float) -> NDArray | float:
        """Depth noise std (m) at depth ``depth_m`` (m)."""
        return self.sigma_base_m + self.sigma_z2_m_per_m2 * np.square(depth_m)


def frame_rng(seed: int, camera: str, t: float) -> np.random.Generator:
    """The generator of one frame: a pure function of seed, camera name and time (exact bits)."""
    t_bits = int(np.float64(t).view(np.uint64))
    entropy = [int(seed), zlib.crc32(camera.encode()), t_bits & 0xFFFFFFFF, t_bits >> 32]
    return np.random.default_rng(np.random.SeedSequence(entropy))


def _neighbour_extremes(z: Depth, valid: NDArray[np.bool_]) -> tuple[Depth, Depth]:
    hi = np.where(valid, z, -np.inf).astype(np.float32)
    lo = np.where(valid, z, np.inf).astype(np.float32)
    z_max, z_min = hi.copy(), lo.copy()
    for src, dst in ((np.s_[:-1], np.s_[1:]), (np.s_[1:], np.s_[:-1])):
        np.maximum(z_max[dst], hi[src], out=z_max[dst])
        np.minimum(z_min[dst], lo[src], out=z_min[dst])
        np.maximum(z_max[:, dst], hi[:, src], out=z_max[:, dst])
        np.minimum(z_min[:, dst], lo[:, src], out=z_min[:, dst])
    return z_min, z_max


def apply_depth_noise(
    depth_m: Depth,
    config: DepthNoiseConfig,
    rng: np.random.Generator,
    cos_incidence: NDArray[np.float32] | None = None,
) -> Depth:
    """Noisy copy of an ideal depth image.

    Parameters
    ----------
    depth_m
        ``(H, W)`` ideal depth along the camera axis, m; 0, NaN or inf where nothing was hit.
    config
        The noise parameters.
    rng
        Source of randomness (see :func:`frame_rng`).
    cos_incidence
        ``(H, W)`` ``|cos|`` of the angle between ray and surface normal; needed only for
        grazing dropouts (ignored when None).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 depth in m, 0 where invalid.
    """
    z = np.array(depth_m, dtype=np.float32)
    valid = np.isfinite(z) & (z > 0)
    z[~valid] = 0.0

    if config.flying_pixel_probability > 0:
        z_min, z_max = _neighbour_extremes(z, valid)
        edge = np.flatnonzero(valid & (z_max - z_min > config.edge_jump_m))
        if edge.size:
            fly = edge[rng.random(edge.size) < config.flying_pixel_probability]
            lo, hi = z_min.reshape(-1)[fly], z_max.reshape(-1)[fly]
            z.reshape(-1)[fly] = lo + rng.random(fly.size, dtype=np.float32) * (hi - lo)

    idx = np.flatnonzero(valid)
    zv = z.reshape(-1)[idx]
    if config.sigma_base_m > 0 or config.sigma_z2_m_per_m2 > 0:
        sigma = np.float32(config.sigma_base_m) + np.float32(config.sigma_z2_m_per_m2) * zv * zv
        zv += sigma * rng.standard_normal(zv.size, dtype=np.float32)
    if config.quantisation_m > 0:
        q = np.float32(config.quantisation_m)
        zv = np.round(zv / q) * q

    drop = np.zeros(zv.size, dtype=bool)
    p_base = config.dropout_fraction
    cos_start = math.cos(math.radians(config.grazing_start_deg))
    grazing = cos_incidence is not None and config.grazing_dropout > 0 and cos_start > 1e-9
    if p_base > 0 or grazing:
        p: NDArray[np.float32] | float = p_base
        if grazing:
            c = np.asarray(cos_incidence, dtype=np.float32).reshape(-1)[idx]
            ramp = np.clip((cos_start - c) / np.float32(cos_start), 0.0, 1.0)
            p = p_base + np.float32(config.grazing_dropout) * ramp
        drop = rng.random(zv.size, dtype=np.float32) < p
    drop |= (zv < config.min_depth_m) | (zv > config.max_depth_m)
    zv[drop] = 0.0
    z.reshape(-1)[idx] = zv
    return z

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

The random numbers are counter-based, not drawn in sequence: every draw is a hash (splitmix64)
of the frame's key (:func:`frame_key`: seed, camera name, time) and the pixel's index in the
image, so a pixel's noise depends only on the frame, its index and its own (and, for flying
pixels, its 4 neighbours') ideal depth. A render of part of the image (a region of interest plus
:data:`NOISE_MARGIN_PX` pixels for the neighbours) is therefore bit for bit the full render there.
The random bits are integer arithmetic, the same on every machine; the normal deviate goes through
numpy's float32 ``log`` and ``cos``, whose last bit may differ between CPUs, but never between two
elements of different arrays on one machine (element-wise, no reductions).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Self

import numpy as np
from numpy.typing import NDArray

from ..config import StageConfig, param
from ..errors import ConfigError, InputError

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


#: Pixels beyond a region of interest whose ideal depth its noise needs (flying pixels look at
#: the 4-neighbourhood).
NOISE_MARGIN_PX = 1

_MASK64 = (1 << 64) - 1
_GAMMA = 0x9E3779B97F4A7C15  # splitmix64's increment (2^64 / golden ratio, odd)
_MIX1 = 0xBF58476D1CE4E5B9
_MIX2 = 0x94D049BB133111EB
# Independent 64-bit draws per pixel: the counter of draw j of pixel i is i * _DRAWS + j.
_DRAWS = 3
_NORMAL, _DROP_FLY, _FLY_AT = range(_DRAWS)
_U24 = np.float32(2.0**-24)


def _mix_int(z: int) -> int:
    """splitmix64's output function on a Python int (the frame key, once per frame)."""
    z = ((z ^ (z >> 30)) * _MIX1) & _MASK64
    z = ((z ^ (z >> 27)) * _MIX2) & _MASK64
    return z ^ (z >> 31)


def frame_key(seed: int, camera: str, t: float) -> int:
    """The 64-bit key of one frame's noise: a pure function of seed, camera name and time bits."""
    t_bits = int(np.float64(t).view(np.uint64))
    key = 0
    for word in (int(seed), zlib.crc32(camera.encode()), t_bits):
        key = _mix_int(((key ^ word) + _GAMMA) & _MASK64)
    return key


def pixel_bits(key: int, index: NDArray[np.integer], draw: int) -> NDArray[np.uint64]:
    """64 random bits per pixel: splitmix64 with seed ``key`` at counter ``index * 3 + draw``.

    ``index`` is the pixel's flat index ``row * width + col`` in the whole image; ``draw`` (0-2)
    picks one of the pixel's independent draws. Integer multiplications wrap modulo 2^64.
    """
    z = np.asarray(index, dtype=np.uint64) * np.uint64(_DRAWS) + np.uint64(draw)
    z *= np.uint64(_GAMMA)
    z += np.uint64(key)
    z ^= z >> np.uint64(30)
    z *= np.uint64(_MIX1)
    z ^= z >> np.uint64(27)
    z *= np.uint64(_MIX2)
    z ^= z >> np.uint64(31)
    return z


def _uniform_hi(bits: NDArray[np.uint64]) -> NDArray[np.float32]:
    """Uniform in [0, 1) from the top 24 bits (exact in float32)."""
    return (bits >> np.uint64(40)).astype(np.float32) * _U24


def _uniform_lo(bits: NDArray[np.uint64]) -> NDArray[np.float32]:
    """Uniform in [0, 1) from bits 8-31, independent of :func:`_uniform_hi`."""
    return ((bits >> np.uint64(8)) & np.uint64(0xFFFFFF)).astype(np.float32) * _U24


def _standard_normal(bits: NDArray[np.uint64]) -> NDArray[np.float32]:
    """One N(0, 1) per pixel by Box-Muller on two 24-bit uniforms of its draw.

    ``u1`` in (0, 1] (never 0: no log(0)), so |n| <= sqrt(2 ln 2^24) = 5.8: a tail cut at a
    probability of 7e-9 a pixel, far below anything a frame of 0.4 M pixels shows. float32
    throughout (twice the SIMD lanes of float64; the depth is float32 anyway).
    """
    u1 = _uniform_hi(bits)
    u1 += _U24  # (0, 1]
    u2 = _uniform_lo(bits)
    r = np.log(u1)
    r *= np.float32(-2.0)
    np.sqrt(r, out=r)
    u2 *= np.float32(2.0 * math.pi)
    return r * np.cos(u2)


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
    key: int,
    cos_incidence: NDArray[np.float32] | None = None,
    *,
    origin: tuple[int, int] = (0, 0),
    image_width: int | None = None,
) -> Depth:
    """Noisy copy of an ideal depth image, or of a part of one.

    Parameters
    ----------
    depth_m
        ``(H, W)`` ideal depth along the camera axis, m; 0, NaN or inf where nothing was hit.
    config
        The noise parameters.
    key
        The frame's noise key (:func:`frame_key`).
    cos_incidence
        ``(H, W)`` ``|cos|`` of the angle between ray and surface normal; needed only for
        grazing dropouts (ignored when None).
    origin, image_width
        Where ``depth_m`` lies in the whole image: ``(row, col)`` of its first pixel and the
        whole image's width (default: ``depth_m`` is the whole image). Pixels are keyed by their
        index in the whole image, so a part gets the same noise as the whole; its edge pixels
        lack the neighbours outside it, so pass :data:`NOISE_MARGIN_PX` more pixels on every
        side that is not the image's edge and discard them.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 depth in m, 0 where invalid.
    """
    z = np.array(depth_m, dtype=np.float32)
    valid = np.isfinite(z) & (z > 0)
    z[~valid] = 0.0
    h, w = z.shape
    width = w if image_width is None else int(image_width)
    row0, col0 = origin
    if not (0 <= col0 and col0 + w <= width and row0 >= 0):
        raise InputError(f"origin = {origin}: a {h}x{w} part does not fit an image {width} wide")

    idx = np.flatnonzero(valid)
    if (row0, col0, width) == (0, 0, w):
        pixel = idx
    else:
        # The pixel's identity is its flat index in the whole image, not in this part.
        r, c = np.divmod(idx, w)
        pixel = (r + row0) * np.int64(width) + (c + col0)
    p_base = config.dropout_fraction
    cos_start = math.cos(math.radians(config.grazing_start_deg))
    grazing = cos_incidence is not None and config.grazing_dropout > 0 and cos_start > 1e-9
    flying = config.flying_pixel_probability > 0
    # One draw per pixel serves the dropout (top bits) and the flying decision (low bits).
    bits = pixel_bits(key, pixel, _DROP_FLY) if (p_base > 0 or grazing or flying) else None

    if flying and bits is not None:
        z_min, z_max = _neighbour_extremes(z, valid)
        at_edge = (z_max - z_min > config.edge_jump_m).reshape(-1)[idx]
        if at_edge.any():
            fly = at_edge & (_uniform_lo(bits) < np.float32(config.flying_pixel_probability))
            flat, where = idx[fly], pixel[fly]
            lo, hi = z_min.reshape(-1)[flat], z_max.reshape(-1)[flat]
            z.reshape(-1)[flat] = lo + _uniform_hi(pixel_bits(key, where, _FLY_AT)) * (hi - lo)

    zv = z.reshape(-1)[idx]
    if config.sigma_base_m > 0 or config.sigma_z2_m_per_m2 > 0:
        sigma = np.float32(config.sigma_base_m) + np.float32(config.sigma_z2_m_per_m2) * zv * zv
        zv += sigma * _standard_normal(pixel_bits(key, pixel, _NORMAL))
    if config.quantisation_m > 0:
        q = np.float32(config.quantisation_m)
        zv = np.round(zv / q) * q

    drop = np.zeros(zv.size, dtype=bool)
    if (p_base > 0 or grazing) and bits is not None:
        p: NDArray[np.float32] | np.float32 = np.float32(p_base)
        if grazing:
            c = np.asarray(cos_incidence, dtype=np.float32).reshape(-1)[idx]
            ramp = np.clip((cos_start - c) / np.float32(cos_start), 0.0, 1.0)
            p = np.float32(p_base) + np.float32(config.grazing_dropout) * ramp
        drop = _uniform_hi(bits) < p
    drop |= (zv < config.min_depth_m) | (zv > config.max_depth_m)
    zv[drop] = 0.0
    z.reshape(-1)[idx] = zv
    return z

"""Argument checks shared by every public function (one helper, the argument named in the error)."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

FloatArray = NDArray[np.float64]


def as_points(points: ArrayLike, name: str = "points", *, dtype: type = np.float64) -> NDArray:
    """Return ``points`` as a C-contiguous ``(N, 3)`` float array.

    Raises
    ------
    InputError
        (a ``ValueError``) naming ``name`` if the array is not ``(N, 3)`` or not real numbers.
        NaN and inf are allowed here; use :func:`drop_nonfinite` to remove those rows.
    """
    arr = np.asarray(points)
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise InputError(f"{name}: expected real numbers, got dtype {arr.dtype}")
    if arr.ndim == 1 and arr.size == 0:
        arr = arr.reshape(0, 3)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected shape (N, 3), got {arr.shape}")
    return np.ascontiguousarray(arr, dtype=dtype)


def as_vector3(vector: ArrayLike, name: str = "vector") -> FloatArray:
    """Return a finite ``(3,)`` float64 vector, or raise :class:`InputError` naming ``name``."""
    arr = np.asarray(vector)
    if arr.dtype == object or not (
        np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    ):
        raise InputError(f"{name}: expected 3 real numbers, got dtype {arr.dtype}")
    arr = arr.astype(np.float64).reshape(-1) if arr.size == 3 else arr
    if arr.shape != (3,):
        raise InputError(f"{name}: expected shape (3,), got {np.shape(vector)}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: must be finite, got {arr.tolist()}")
    return arr


def as_unit_vector3(vector: ArrayLike, name: str = "vector") -> FloatArray:
    """Return ``vector`` normalised to unit length; raise :class:`InputError` if it is ~zero."""
    arr = as_vector3(vector, name)
    norm = float(np.linalg.norm(arr))
    if not norm > 1e-12:
        raise InputError(f"{name}: must be a non-zero direction, got {arr.tolist()}")
    return arr / norm


def drop_nonfinite(points: NDArray) -> NDArray:
    """Rows of ``points`` whose three coordinates are all finite (NaN and inf rows dropped)."""
    if points.shape[0] == 0:
        return points
    keep = np.isfinite(points).all(axis=1)
    return points if keep.all() else points[keep]


def as_finite_scalar(value: object, name: str) -> float:
    """Return ``value`` as a finite float, or raise :class:`InputError` naming ``name``."""
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a number, got {value!r}") from None
    if not np.isfinite(out):
        raise InputError(f"{name}: must be finite, got {out}")
    return out


def read_only(arr: NDArray) -> NDArray:
    """``arr`` itself, marked read-only: for arrays the caller has just created."""
    arr.setflags(write=False)
    return arr


def read_only_view(arr: NDArray) -> NDArray:
    """A read-only view of ``arr``; ``arr`` (perhaps the caller's own) stays writeable."""
    view = arr.view()
    view.setflags(write=False)
    return view


def read_only_copy(value: ArrayLike, dtype: type = np.float64) -> NDArray:
    """A read-only copy of ``value`` as ``dtype``."""
    return read_only(np.array(value, dtype=dtype))

"""The rows a controller task or a haptic constraint hands to the hierarchy.

Decision variables are ``x = [qdd; tau]`` (``2 * n_joints``). A task is either equalities
``A x = b`` or inequalities ``G x <= h``; both are named tuples so an assembled problem can be
inspected and plotted. A level of the hierarchy stacks the rows of its tasks.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError

FloatArray = NDArray[np.float64]


class Equality(NamedTuple):
    """``A x = b`` with ``A`` of shape ``(m, 2 n)`` and ``b`` of shape ``(m,)``."""

    A: FloatArray
    b: FloatArray
    name: str = ""


class Inequality(NamedTuple):
    """``G x <= h`` with ``G`` of shape ``(m, 2 n)`` and ``h`` of shape ``(m,)``."""

    G: FloatArray
    h: FloatArray
    name: str = ""


def empty_inequality(n_vars: int, name: str = "") -> Inequality:
    """An inequality task with no rows (a constraint that is inactive this tick)."""
    return Inequality(np.zeros((0, n_vars)), np.zeros(0), name)


def task_parts(task: object, where: str) -> tuple[object, object, bool]:
    """``(matrix, right-hand side, is equality)`` of ``task``, unconverted; ``where`` names the
    place in the message (``"level 3"``) when ``task`` is neither kind."""
    if isinstance(task, Equality):
        return task.A, task.b, True
    if isinstance(task, Inequality):
        return task.G, task.h, False
    raise InputError(f"{where}: expected Equality or Inequality, got {type(task).__name__}")

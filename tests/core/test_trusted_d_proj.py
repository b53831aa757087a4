"""The trusted ``d_proj`` kernel (the display's 800 Hz fused rows) against the checked one."""

from __future__ import annotations

import numpy as np
from hapticloud.core.haptics import d_proj, trusted_d_proj
from hypothesis import given
from hypothesis import strategies as st

_coord = st.floats(-10.0, 10.0, allow_nan=False)


@given(
    st.tuples(_coord, _coord, _coord),
    st.tuples(_coord, _coord, _coord),
    st.tuples(_coord, _coord, _coord),
    st.floats(0.0, 0.1),
)
def test_trusted_d_proj_is_d_proj_for_unit_normals(c: tuple, n: tuple, h: tuple, r: float) -> None:
    normal = np.array(n)
    length = float(np.linalg.norm(normal))
    if length < 1e-6:
        return
    normal = normal / length
    centroid, hip = np.array(c), np.array(h)
    # d_proj normalises the normal again (a unit normal's length is 1 within an ulp or two).
    scale = 1.0 + float(np.abs(centroid).sum() + np.abs(hip).sum())
    assert abs(trusted_d_proj(centroid, normal, hip, r) - d_proj(centroid, normal, hip, r)) <= (
        1e-14 * scale
    )

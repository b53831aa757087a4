"""The one estimate encoding: the pipe's tuple and the recordings' dict carry the same fields."""

from __future__ import annotations

import numpy as np
from hapticloud.core.perception import SurfaceEstimate
from hapticloud.hardware.control.messages import (
    ESTIMATE_WIRE_FIELDS,
    estimate_from_dict,
    estimate_from_wire,
    estimate_to_dict,
    estimate_to_wire,
)


def _estimate() -> SurfaceEstimate:
    return SurfaceEstimate(
        1.25,
        "front",
        np.array([0.1, 0.2, 1.0]),
        np.array([0.0, 0.0, 1.0]),
        True,
        reason="",
        method="curvature",
        quality=0.7,
        seq=42,
        free_m=0.0,
        hip=np.array([0.1, 0.2, 1.05]),
        residual_m=0.0012,
    )


def test_the_pipe_and_the_file_carry_every_field_the_fusion_reads() -> None:
    est = _estimate()
    for back in (
        estimate_from_wire(estimate_to_wire(est)),
        estimate_from_dict(estimate_to_dict(est)),
    ):
        assert (back.t, back.camera, back.valid, back.quality, back.seq) == (
            1.25,
            "front",
            True,
            0.7,
            42,
        )
        assert (back.reason, back.method, back.free_m) == ("", "curvature", 0.0)
        np.testing.assert_array_equal(back.centroid, est.centroid)
        np.testing.assert_array_equal(back.hip, est.hip)
        assert back.residual_m == 0.0012
    assert list(estimate_to_dict(est)) == list(ESTIMATE_WIRE_FIELDS)


def test_a_recording_made_before_the_fit_noise_was_carried_reads_it_as_unknown() -> None:
    data = estimate_to_dict(_estimate())
    del data["residual_m"]
    assert estimate_from_dict(data).residual_m == 0.0

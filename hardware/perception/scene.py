"""A scene's cameras as the worker's channels, and the control process's robot as its feed.

:func:`scene_channels` turns an assembled scene (as ``hapticloud run`` builds it) into
channels: a ``d435`` camera is a stepping ``"simulated"`` source from the registry over the
scene's moving world, with the scene's pipeline; an ``oracle`` camera is the scene's oracle
(the true closest point with the scene's noise, no image). :func:`link_occluders` gives the
robot's link capsules at a pose, as the simulator renders and crops them.
:class:`StateBlockFeed` reads the control process's
:class:`~hapticloud.hardware.control.shared_state.RobotStateBlock`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from ..sources import open_source
from .channels import CameraChannel, Capture, ChannelSpec, RenderedChannel, RobotPose
from .sinks import ControlSink, RecorderSink
from .worker import PerceptionWorker

__all__ = [
    "OracleChannel",
    "StateBlockFeed",
    "link_occluders",
    "scene_channels",
    "scene_sim",
    "session_worker",
]


def channel_spec(cam: Any) -> ChannelSpec:
    """The schedule and admission of a scene camera (a ``SimCamera``)."""
    spec = cam.spec
    return ChannelSpec(
        spec.name,
        rate_hz=spec.rate_hz,
        phase_s=cam.phase_s,
        latency_s=spec.latency_s,
        min_quality=spec.min_quality,
        fuse_fallbacks=spec.fuse_fallbacks,
    )


class OracleChannel(CameraChannel):
    """A scene's oracle camera: the true closest body point with the scene's noise (``rng``:
    the scene's seeded stream, one for all of its oracles, as the closed loop draws it)."""

    sees_occluders = False

    def __init__(self, parts: Any, cam: Any, rng: np.random.Generator) -> None:
        super().__init__(channel_spec(cam))
        self._parts = parts
        self._cam = cam
        self._rng = rng

    def capture(
        self, t_scene: float, pose: RobotPose, occluders: Sequence[Any], full_frame: bool
    ) -> Capture:
        return Capture(self._parts.oracle_estimate(self._cam, t_scene, pose.hip, self._rng))

    def close(self) -> None:
        """Nothing to release: the scene is the caller's."""


def scene_channels(parts: Any) -> list[CameraChannel]:
    """The channels of an assembled scene's cameras (an
    :class:`~hapticloud.core.scene.assembly.Assembly`; see the module docstring)."""
    from hapticloud.core.scene.assembly import seeded_noise

    rng = seeded_noise(parts.scene)
    channels: list[CameraChannel] = []
    for cam in parts.cameras:
        if cam.camera is None:
            channels.append(OracleChannel(parts, cam, rng))
            continue
        spec = channel_spec(cam)
        source = open_source(
            "simulated",
            camera=cam.camera,
            world=parts.world.at,
            rate_hz=spec.rate_hz,
            phase_s=spec.phase_s,
            realtime=False,
        )
        channels.append(RenderedChannel(spec, source, cam.pipeline))
    return channels


def link_occluders(model: Any) -> Callable[[RobotPose], Sequence[Any]]:
    """The robot's link capsules at a pose (``model``: a
    :class:`~hapticloud.core.robot.RobotModel`); none for a pose without joints."""

    def occluders(pose: RobotPose) -> Sequence[Any]:
        return () if pose.q is None else model.link_capsules(pose.q)

    return occluders


class StateBlockFeed:
    """The robot's pose from a control process's shared state block (``None`` before its first
    tick, or while the state is not finite)."""

    def __init__(self, block_name: str, n_joints: int) -> None:
        from ..control.shared_state import RobotStateBlock

        self._block = RobotStateBlock.attach(block_name, n_joints)

    def read(self) -> RobotPose | None:
        st = self._block.read()
        if st is None or not (np.isfinite(st.hip_m).all() and np.isfinite(st.q_rad).all()):
            return None
        return RobotPose(st.t, st.hip_m, st.q_rad)

    def close(self) -> None:
        self._block.close()


def scene_sim(scene: str, overrides: dict[str, Any] | None) -> Any:
    """The scene's parts as ``hapticloud run`` builds them (its cameras, world and robot: an
    :class:`~hapticloud.core.scene.assembly.Assembly`)."""
    from hapticloud.core.scene import load_scene
    from hapticloud.core.scene.assembly import assemble

    return assemble(load_scene(scene, overrides))


def session_worker(
    scene: str,
    overrides: dict[str, Any] | None,
    block_name: str,
    n_joints: int,
    estimates: Any,
    record_sink: Any = None,
) -> PerceptionWorker:
    """The worker of ``run --hardware`` (a :class:`~.process.PerceptionProcess`'s ``build``):
    the scene's cameras against the control process's robot (its state block ``block_name``),
    every estimate down its ``estimates`` pipe and, with ``record_sink``, each rendered frame to
    a recorder."""
    from hapticloud.core.threads import settle_numerics

    settle_numerics(1)
    sim = scene_sim(scene, overrides)
    sinks: list[Any] = [ControlSink(estimates)]
    if record_sink is not None:
        sinks.append(RecorderSink(record_sink))
    return PerceptionWorker(
        scene_channels(sim),
        StateBlockFeed(block_name, n_joints),
        sinks,
        occluders=link_occluders(sim.robot),
    )

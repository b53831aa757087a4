"""The 3D view: one object owns the pyvista plotter, the canvas that shows it, and every named
actor in it.

Actors are created once, when the scene's geometry is known (:meth:`SceneView.set_geometry`), and
a frame (:meth:`SceneView.show_snapshot`) only writes new point arrays or transforms into them and
asks for one repaint. Re-adding actors per frame costs about 30 ms (the issue's measurement); the
in-place update of two 5000-point clouds and every overlay costs 3.4 ms (median, measured by
``tests/app/test_app_view_rate.py``); the paint after it is the rest of a frame.

Why ``update()`` and not ``render()``: the canvas (:class:`~hapticloud.app.view_canvas.ViewCanvas`)
renders VTK in every paint, so ``plotter.render()`` followed by a repaint renders twice.
``QWidget.update()`` schedules exactly one paint, and Qt coalesces several requests between two
event-loop turns into one.

Layers and their colours are named in :data:`LAYERS`; the window builds its toggles from it.
"""

from __future__ import annotations

import functools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyvista as pv
from hapticloud.core.geometry.primitives import Box, Capsule, Primitive, Sphere
from hapticloud.core.haptics.unknown import UnknownSpaceConfig
from hapticloud.hardware.live.contract import CameraFrame, SceneGeometry, Snapshot, SourceState
from numpy.typing import NDArray
from PyQt6 import QtCore, QtWidgets
from vtkmodules.vtkCommonMath import vtkMatrix4x4

from .view_canvas import ViewCanvas

FloatArray = NDArray[np.float64]

# Cameras in saturated blue / green / purple (ColorBrewer Paired), away from the bodies' muted
# skin tone and from the fused (magenta) and HIP (amber) markers.
CAMERA_COLOURS = ("#1f78b4", "#33a02c", "#6a3d9a", "#b15928", "#a6cee3", "#b2df8a")
STAGE_COLOURS = {
    "kept": "#ff7f00",  # orange, cyan: unlike any camera's colour (estimates keep those)
    "filled": "#17becf",
    "rejected": "#e41a1c",
    "cropped": "#a8a8a8",
}
FUSED_COLOUR = "#e7298a"
TRUTH_COLOUR = "#111111"
HIP_COLOUR = "#ffbf00"
ROBOT_COLOUR = "#8a9bb0"
#: The exoskeleton is drawn as a ghost: its links sit between the view and the HIP (the hand
#: holds the handle), and the clouds, shells and normals behind them are what is to be seen.
ROBOT_OPACITY = 0.15
#: The fused surface is drawn while its newest estimate is at most this old (s): the surface
#: guard's ``fresh_s``, after which the tick holds it as unknown.
FUSED_SHOWN_MAX_AGE_S = UnknownSpaceConfig().fresh_s
BODY_COLOUR = "#e2d6ca"
BODY_INSET_M = 0.003
SHELL_COLOUR = "#5aa9e6"
FORCE_COLOUR = "#d95f02"
#: Length of the constraint force arrow per newton (m/N): 20 N draws 100 mm.
FORCE_SCALE_M_PER_N = 0.005
#: Forces below this (N) hide the arrow; longer than FORCE_MAX_M it is capped (its length then
#: says "at least").
FORCE_MIN_N = 0.05
FORCE_MAX_M = 0.25
#: A shorter force arrow keeps the cross-section of one this long (m).
FORCE_MIN_WIDTH_M = 0.06
REJECTED_GREY = (150, 150, 150)
BACKGROUND = ("#fdfdfd", "#dfe6ee")

COLOR_MODES = ("camera", "stage")


@dataclass(frozen=True)
class Layer:
    """A group of actors switched on and off together."""

    key: str
    label: str
    visible: bool = True


LAYERS = (
    Layer("clouds", "clouds"),
    Layer("context", "scene points (cropped)", False),
    Layer("bodies", "true surface"),
    Layer("truth", "true closest point"),
    Layer("robot", "robot"),
    Layer("shells", "shells"),
    Layer("estimates", "camera estimates"),
    Layer("fused", "fused estimate"),
    Layer("force", "constraint force (session)"),
)

#: Camera presets: key -> label. "follow" keeps the HIP centred as it moves.
CAMERA_PRESETS = {"follow": "follow HIP", "overview": "overview", "front": "front", "side": "side"}
# Where the presets look from (world frame: x out of the chest, y to the patient's left, z up).
# The demo's handle leaves the HIP forward, to the patient's right and down, so views from the
# patient's left see the surface patch beside the HIP instead of the robot; "side" shows the gap
# between HIP and surface (d_proj) in profile.
_FOCUS = np.array([0.12, 0.0, 1.06])
_PRESET_OFFSETS = {
    # ~45 deg off the surface normal at the chest and the face: the patch beside the HIP shows.
    "follow": np.array([0.26, 0.42, 0.26]),
    "overview": np.array([0.95, 0.72, 0.42]),
    "front": np.array([1.3, 0.0, 0.12]),
    "side": np.array([0.05, 1.3, 0.1]),
}

_ARROW_M = 0.06  # estimate normals are drawn this long
#: The caption (time, frame) is rewritten at most this often (s): a changed text is rasterised
#: and uploaded as a new texture, ~5 % of the window's thread at every frame in software GL.
CAPTION_PERIOD_S = 0.25
_SHELL_NORMAL_M = 0.025
_CIRCLE_SEGMENTS = 48
_EMPTY = np.zeros((1, 3))


def _hex_rgb(colour: str) -> tuple[int, int, int]:
    colour = colour.lstrip("#")
    return int(colour[0:2], 16), int(colour[2:4], 16), int(colour[4:6], 16)


def _basis(direction: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Unit ``w`` along ``direction`` and unit ``u``, ``v`` spanning the plane normal to it.

    Plain float arithmetic: called ~15 times per frame, where ``np.cross`` on 3-vectors costs
    ~40 us a call.
    """
    x, y, z = (float(c) for c in direction)
    n = math.sqrt(x * x + y * y + z * z) or 1e-12
    x, y, z = x / n, y / n, z / n
    # u = w x helper, helper = e_x unless w is near e_x (then e_y)
    if abs(x) < 0.9:
        ux, uy, uz = 0.0, z, -y
    else:
        ux, uy, uz = -z, 0.0, x
    m = math.sqrt(ux * ux + uy * uy + uz * uz)
    ux, uy, uz = ux / m, uy / m, uz / m
    v = (y * uz - z * uy, z * ux - x * uz, x * uy - y * ux)
    return np.array((ux, uy, uz)), np.array(v), np.array((x, y, z))


def _placement(
    origin: FloatArray, x_axis: FloatArray, scale: float, width: float | None = None
) -> FloatArray:
    """4x4 matrix taking a template's +x axis to ``x_axis`` at ``origin``, scaled by ``scale``
    along it and by ``width`` (default ``scale``) across it."""
    u, v, w = _basis(np.asarray(x_axis, dtype=np.float64))
    across = scale if width is None else width
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = w * scale, u * across, v * across
    m[:3, 3] = origin
    return m


def _scaled_at(center: FloatArray, scale: float) -> FloatArray:
    m = np.diag([scale, scale, scale, 1.0])
    m[:3, 3] = center
    return m


def _vertex_cells(n: int) -> pv.CellArray:
    return pv.CellArray.from_regular_cells(np.arange(n, dtype=np.int64).reshape(-1, 1))


def _set_cloud(mesh: pv.PolyData, points: NDArray | None) -> bool:
    """Write ``points`` into ``mesh`` in place; False when there is nothing to show."""
    if points is None or len(points) == 0:
        return False
    if mesh.n_points != len(points):
        mesh.points = points
        mesh.verts = _vertex_cells(len(points))
    else:
        mesh.points = points
    return True


@functools.cache
def _unit_sphere() -> pv.PolyData:
    """The shells' template (shared, never modified)."""
    return pv.Sphere(radius=1.0, theta_resolution=28, phi_resolution=18)


def _great_circles(segments: int = 96) -> pv.PolyData:
    """Three orthogonal unit circles: the workspace sphere's outline without a mesh over it."""
    theta = np.linspace(0.0, 2.0 * math.pi, segments, endpoint=False)
    c, s = np.cos(theta), np.sin(theta)
    zero = np.zeros_like(theta)
    rings = [np.column_stack(xyz) for xyz in ((c, s, zero), (c, zero, s), (zero, c, s))]
    lines = []
    for k in range(3):
        idx = np.arange(k * segments, (k + 1) * segments)
        lines += [segments + 1, *idx, idx[0]]
    return pv.PolyData(np.vstack(rings), lines=np.array(lines))


def _capsule_template(radius_steps: int = 16) -> tuple[pv.PolyData, NDArray[np.bool_]]:
    """A unit-radius sphere along +z whose upper half is moved by the capsule's length."""
    sphere = pv.Sphere(
        radius=1.0, theta_resolution=radius_steps, phi_resolution=radius_steps + 1
    )  # odd phi: a ring of vertices on the equator, so the stretched band is a true cylinder
    upper = np.asarray(sphere.points[:, 2] > 1e-6)
    return sphere, upper


class SceneView(QtWidgets.QWidget):
    """The 3D view of the perception pipeline, fed frozen snapshots.

    Call :meth:`set_geometry` once per source (creates every actor), then
    :meth:`show_snapshot` per displayed frame (updates them in place and schedules one paint).
    """

    #: The render scale of views made without one: ``None`` is ``auto`` (see
    #: :data:`~hapticloud.app.view_canvas.SOFTWARE_RENDER_SCALE`); ``hapticloud app
    #: --render-scale`` sets it.
    default_render_scale: float | None = None

    def __init__(
        self, parent: QtWidgets.QWidget | None = None, *, render_scale: float | None = None
    ) -> None:
        super().__init__(parent)
        # Measured in software GL (llvmpipe, 880x500 view, two 5000-point clouds and every
        # overlay): pyvista's 8x MSAA halves the frame rate; its 5-light kit costs ~15 % over a
        # headlight and a key light; VTK's order-independent transparency (on by default when
        # depth peeling is off) costs ~25 %. Without it translucent layers blend in actor order,
        # which for these faint overlays is indistinguishable.
        scale = self.default_render_scale if render_scale is None else render_scale
        self.plotter = pv.Plotter(off_screen=True, lighting="none")
        self.plotter.ren_win.SetMultiSamples(0)
        self.plotter.renderer.SetUseOIT(False)
        self.plotter.add_light(pv.Light(light_type="headlight", intensity=0.75))
        # Camera-light coordinates: the camera at +z looking at the origin, +y up: upper left.
        key = pv.Light(position=(-0.5, 0.9, 1.0), light_type="camera light", intensity=0.45)
        self.plotter.add_light(key)
        self.plotter.set_background(BACKGROUND[0], top=BACKGROUND[1])
        #: The widget that shows the plotter's frames and hands it the mouse.
        self.canvas = ViewCanvas(self, self.plotter, scale)
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.canvas)
        self.setMinimumSize(320, 240)
        self._meshes: dict[str, pv.PolyData] = {}
        self._actors: dict[str, pv.Actor] = {}
        self._layers: dict[str, list[str]] = {layer.key: [] for layer in LAYERS}
        self._layer_on = {layer.key: layer.visible for layer in LAYERS}
        # Actors that have data this frame: a layer toggle never shows an empty one.
        self._has_data: dict[str, bool] = {}
        self._layer_of: dict[str, str | None] = {}
        self._matrices: dict[str, vtkMatrix4x4] = {}
        self._geometry: SceneGeometry | None = None
        self._color_mode = "camera"
        self._preset = "follow"
        self._last_hip: FloatArray | None = None
        self._shell_count = -1
        self._stop_shown = False
        self._caption_t = -math.inf
        #: The (length, radius) each robot capsule's mesh is built for (m).
        self._capsule_dims: dict[str, tuple[float, float]] = {}
        self._capsule, self._capsule_upper = _capsule_template()
        self._capsule_normals = np.array(self._capsule.point_data["Normals"])
        self.frames_shown = 0
        self.force_n = 0.0
        # Point sizes and line widths at full scale, applied x the render scale (text follows
        # the render window's DPI, which the interactor scales).
        self._sizes: dict[str, tuple[float, float]] = {}
        self.canvas.on_scale.append(self._rescale)

    @property
    def render_scale(self) -> float | None:
        """The VTK render window's pixels per widget pixel (``None`` until the first resize
        decides ``auto``)."""
        return self.canvas.render_scale

    def _rescale(self, scale: float) -> None:
        for name in self._sizes:
            self._size_actor(name)

    def _size_actor(self, name: str) -> None:
        point, line = self._sizes[name]
        scale = self.canvas.render_scale or 1.0
        prop = self._actors[name].GetProperty()
        prop.SetPointSize(point * scale)
        prop.SetLineWidth(line * scale)

    # ----- building (once per source) ----------------------------------------------------------
    def _add(
        self,
        name: str,
        mesh: pv.PolyData,
        layer: str | None,
        *,
        static: bool = False,
        **kwargs: object,
    ) -> pv.Actor:
        """Create one named actor. Non-static ones stay hidden until a snapshot places them
        (their templates sit at the origin at unit size)."""
        actor = self.plotter.add_mesh(mesh, name=name, render=False, reset_camera=False, **kwargs)
        self._meshes[name] = mesh
        self._actors[name] = actor
        prop = actor.GetProperty()
        self._sizes[name] = (prop.GetPointSize(), prop.GetLineWidth())
        self._size_actor(name)
        self._has_data[name] = static
        self._layer_of[name] = layer
        if layer is not None:
            self._layers[layer].append(name)
        actor.SetVisibility(static)
        return actor

    def set_geometry(self, geometry: SceneGeometry) -> None:
        """Create every actor for ``geometry`` (replacing those of a previous source)."""
        self.plotter.clear_actors()
        self._matrices.clear()
        self._meshes.clear()
        self._actors.clear()
        self._sizes.clear()
        self._has_data.clear()
        for names in self._layers.values():
            names.clear()
        self._geometry = geometry
        self._stop_shown = False
        self._caption_t = -math.inf
        self._capsule_dims.clear()
        self._shell_count = -1

        for body in geometry.bodies:
            faces = np.column_stack((np.full(len(body.faces), 3), body.faces)).ravel()
            mesh = pv.PolyData(np.asarray(body.vertices, dtype=np.float64), faces)
            mesh = mesh.compute_normals(
                cell_normals=False,
                split_vertices=True,
                feature_angle=40.0,
                auto_orient_normals=True,
            )
            # Drawn opaque, BODY_INSET_M inside the true surface: the measured points (on the
            # surface, +-1 mm noise) stay in front of it instead of flickering through it, and
            # an opaque body costs ~20 % less to draw than a translucent one in software GL.
            mesh.points = mesh.points - BODY_INSET_M * mesh.point_data["Normals"]
            self._add(
                f"body:{body.name}",
                mesh,
                "bodies",
                static=True,
                color=BODY_COLOUR,
                opacity=1.0,
                specular=0.15,
                ambient=0.25,
                smooth_shading=True,
            )
        for i, cam in enumerate(geometry.cameras):
            colour = CAMERA_COLOURS[i % len(CAMERA_COLOURS)]
            self._add(
                f"context:{cam.name}",
                pv.PolyData(_EMPTY.copy()),
                "context",
                color=STAGE_COLOURS["cropped"],
                point_size=2,
                opacity=0.55,
                lighting=False,
            )
            for kind in ("cloud", "filled", "rejected"):
                self._add(
                    f"{kind}:{cam.name}",
                    pv.PolyData(_EMPTY.copy()),
                    "clouds",
                    color=colour,
                    point_size=4 if kind == "cloud" else 5,
                    lighting=False,
                )
            self._add(
                f"centroid:{cam.name}",
                pv.Sphere(radius=1.0, theta_resolution=12, phi_resolution=12),
                "estimates",
                color=colour,
            )
            self._add(
                f"normal:{cam.name}",
                pv.Arrow(tip_length=0.3, tip_radius=0.09, shaft_radius=0.03),
                "estimates",
                color=colour,
            )
            # The camera itself: a cone on its optical centre, pointing along its view axis.
            self._add(
                f"camera:{cam.name}",
                pv.Cone(center=cam.origin, direction=-cam.axis, height=0.07, radius=0.035),
                None,
                static=True,
                color=colour,
            )
        self._add(
            "hip",
            pv.Sphere(radius=1.0, theta_resolution=24, phi_resolution=24),
            None,
            color=HIP_COLOUR,
            opacity=0.55,
            smooth_shading=True,
        )
        self._add(
            "workspace",
            _great_circles(),
            "shells",
            color=SHELL_COLOUR,
            opacity=0.6,
            line_width=1,
            lighting=False,
        )
        for i, shape in enumerate(geometry.robot_shapes):
            # Every shape moves by user matrix. A capsule's mesh is its template stretched to
            # the link's length and radius (a stretched sphere keeps its normals), rebuilt only
            # when those change: rewriting ~20 links' points per frame re-uploaded their buffers,
            # ~15 % of the window's thread in software GL (py-spy).
            template = (
                self._capsule.copy()
                if shape == "capsule"
                else pv.Sphere(radius=1.0)
                if shape == "sphere"
                else pv.Cube()
            )
            self._add(
                f"robot:{i}",
                template,
                "robot",
                color=ROBOT_COLOUR,
                opacity=ROBOT_OPACITY,
                lighting=False,
                culling="back",
            )
        self._add(
            "shell_spheres",
            pv.Sphere(radius=1e-3),
            "shells",
            color=SHELL_COLOUR,
            opacity=0.05,
            lighting=False,
            # Only the far half of each shell: nested shells otherwise veil the HIP and the
            # cloud in front of them; the far halves read as concentric bowls behind the scene.
            culling="front",
        )
        for name in ("shell_circles", "shell_normals"):
            mesh = pv.PolyData(_EMPTY.copy())
            mesh.point_data["rgb"] = np.zeros((1, 3), np.uint8)
            self._add(name, mesh, "shells", scalars="rgb", rgb=True, line_width=3, lighting=False)
        self._add(
            "fused_centroid",
            pv.Sphere(radius=1.0, theta_resolution=16, phi_resolution=16),
            "fused",
            color=FUSED_COLOUR,
        )
        self._add(
            "fused_normal",
            pv.Arrow(tip_length=0.3, tip_radius=0.09, shaft_radius=0.035),
            "fused",
            color=FUSED_COLOUR,
        )
        self._add(
            "truth_point",
            pv.Sphere(radius=1.0, theta_resolution=12, phi_resolution=12),
            "truth",
            color=TRUTH_COLOUR,
        )
        self._add(
            "truth_normal",
            pv.Arrow(tip_length=0.3, tip_radius=0.06, shaft_radius=0.015),
            "truth",
            color=TRUTH_COLOUR,
        )
        self._add("gap", pv.Line((0, 0, 0), (1, 0, 0)), "fused", color=FUSED_COLOUR, line_width=2)
        self._add(
            "force",
            pv.Arrow(tip_length=0.25, tip_radius=0.07, shaft_radius=0.025),
            "force",
            color=FORCE_COLOUR,
        )
        self._banner = self.plotter.add_text(
            "STOPPED",
            position=(0.5, 0.96),
            viewport=True,
            font_size=28,
            color="#c0392b",
            name="banner",
        )
        self._banner.prop.SetJustificationToCentered()
        self._banner.prop.SetVerticalJustificationToTop()
        self._banner.prop.bold = True
        self._banner.SetVisibility(False)
        self._caption = self.plotter.add_text(
            " ", position=(0.01, 0.01), viewport=True, font_size=9, color="#333333", name="caption"
        )
        self.plotter.add_axes(interactive=False, line_width=2, labels_off=False)
        for key, on in self._layer_on.items():
            self.set_layer_visible(key, on, render=False)
        self.set_color_mode(self._color_mode, render=False)
        self.set_camera_preset(self._preset, render=False)
        self.request_render()

    # ----- controls -----------------------------------------------------------------------------
    @property
    def actor_names(self) -> tuple[str, ...]:
        return tuple(self._actors)

    def actor_count(self) -> int:
        """Actors in the renderer (the frame-update test checks this never grows)."""
        return len(self.plotter.renderer.actors)

    def actor(self, name: str) -> pv.Actor:
        return self._actors[name]

    def set_layer_visible(self, key: str, visible: bool, *, render: bool = True) -> None:
        self._layer_on[key] = bool(visible)
        for name in self._layers[key]:
            self._actors[name].SetVisibility(visible and self._has_data.get(name, True))
        if render:
            self.request_render()

    def layer_visible(self, key: str) -> bool:
        return self._layer_on[key]

    @property
    def camera_preset(self) -> str:
        return self._preset

    @property
    def color_mode(self) -> str:
        return self._color_mode

    def set_color_mode(self, mode: str, *, render: bool = True) -> None:
        """``"camera"``: each camera's points in its colour; ``"stage"``: by pipeline stage."""
        if mode not in COLOR_MODES:
            raise ValueError(f"color mode {mode!r}: expected one of {', '.join(COLOR_MODES)}")
        self._color_mode = mode
        geometry = self._geometry
        if geometry is None:
            return
        for i, cam in enumerate(geometry.cameras):
            own = CAMERA_COLOURS[i % len(CAMERA_COLOURS)]
            by_camera = mode == "camera"
            self._actors[f"cloud:{cam.name}"].prop.color = (
                own if by_camera else STAGE_COLOURS["kept"]
            )
            self._actors[f"filled:{cam.name}"].prop.color = (
                own if by_camera else STAGE_COLOURS["filled"]
            )
            self._actors[f"rejected:{cam.name}"].prop.color = STAGE_COLOURS["rejected"]
            self._actors[f"context:{cam.name}"].prop.color = (
                _blend(own, "#ffffff", 0.55) if by_camera else STAGE_COLOURS["cropped"]
            )
        if render:
            self.request_render()

    def legend(self) -> list[tuple[str, str]]:
        """``(colour, label)`` pairs for what the view shows now (the window draws them)."""
        items: list[tuple[str, str]] = []
        cameras = self._geometry.cameras if self._geometry is not None else ()
        if self._color_mode == "stage":
            items += [
                (STAGE_COLOURS["kept"], "kept"),
                (STAGE_COLOURS["filled"], "filled (ICP memory)"),
                (STAGE_COLOURS["rejected"], "rejected clusters"),
            ]
            if self._layer_on["context"]:
                items.append((STAGE_COLOURS["cropped"], "cropped"))
        # Estimates and shell circles keep their camera's colour in both modes.
        suffix = "" if self._color_mode == "camera" else " estimates"
        for i, cam in enumerate(cameras):
            items.append((CAMERA_COLOURS[i % len(CAMERA_COLOURS)], cam.name + suffix))
        items += [
            (FUSED_COLOUR, "fused"),
            (TRUTH_COLOUR, "truth"),
            (HIP_COLOUR, "HIP"),
        ]
        if self._layer_on["force"]:
            items.append((FORCE_COLOUR, f"force ({1e3 * FORCE_SCALE_M_PER_N:g} mm/N)"))
        return items

    def set_camera_preset(self, preset: str, *, render: bool = True) -> None:
        """Look from a preset (a key of :data:`CAMERA_PRESETS`): ``follow`` (the HIP, as it
        moves), ``overview``, ``front`` or ``side`` (the patient's left: d_proj in profile)."""
        if preset not in CAMERA_PRESETS:
            raise ValueError(
                f"camera preset {preset!r}: expected one of {', '.join(CAMERA_PRESETS)}"
            )
        self._preset = preset
        focus = _FOCUS
        if preset == "follow" and self._last_hip is not None:
            focus = self._last_hip
        self._place_camera(focus, _PRESET_OFFSETS[preset], 30.0)
        if render:
            self.request_render()

    def _place_camera(self, focus: FloatArray, offset: FloatArray, view_angle: float) -> None:
        # VTK's camera directly: pyvista's setters each reset the clipping range (~0.6 ms).
        cam = self.plotter.renderer.GetActiveCamera()
        cam.SetFocalPoint(*(float(c) for c in focus))
        cam.SetPosition(*(float(c) for c in focus + offset))
        cam.SetViewUp(0.0, 0.0, 1.0)
        cam.SetViewAngle(view_angle)
        self.plotter.renderer.ResetCameraClippingRange()

    def _move(self, name: str, matrix: FloatArray) -> None:
        """Set an actor's placement, re-using its ``vtkMatrix4x4`` (no validation, no copy)."""
        vtk_matrix = self._matrices.get(name)
        if vtk_matrix is None:
            vtk_matrix = self._matrices[name] = vtkMatrix4x4()
            self._actors[name].SetUserMatrix(vtk_matrix)
        vtk_matrix.DeepCopy(matrix.ravel().tolist())

    def request_render(self) -> None:
        """Schedule one paint (which renders VTK once); repeated requests coalesce."""
        self.canvas.update()

    # ----- per frame ----------------------------------------------------------------------------
    def show_snapshot(self, snap: Snapshot) -> None:
        """Update every actor in place from ``snap`` and schedule one paint. Never adds actors."""
        geometry = self._geometry
        if geometry is None:
            return
        self._last_hip = np.asarray(snap.hip)
        r_hip = geometry.r_hip_m
        self._move("hip", _scaled_at(snap.hip, r_hip))
        self._visible("hip", True)
        workspace = snap.config.perception.crop.workspace_radius_m
        self._move("workspace", _scaled_at(snap.hip, workspace))
        self._visible("workspace", True, "shells")

        for body, offset in zip(geometry.bodies, snap.body_offsets, strict=False):
            self._actors[f"body:{body.name}"].position = tuple(offset)

        self._show_robot(snap.robot)
        for frame in snap.cameras:
            self._show_camera(frame)
        self._show_shells(snap)
        self._show_fused(snap)
        self._show_truth(snap)
        now = time.monotonic()
        if now - self._caption_t >= CAPTION_PERIOD_S or snap.state is not SourceState.RUNNING:
            self._caption_t = now
            self._caption.SetInput(
                f"t = {snap.t:6.2f} s   frame {snap.seq}   HIP r = {1e3 * r_hip:.0f} mm"
            )
        if snap.state is SourceState.FAILED:
            self._banner.SetInput("FAILED")
        elif snap.state is SourceState.STOPPED or self._stop_shown:
            # Snapshots published before a requested stop must not hide its banner.
            self._banner.SetInput("STOPPED")
        self._banner.SetVisibility(snap.state is not SourceState.RUNNING or self._stop_shown)
        if self._preset == "follow":
            # Keep the user's orbit and zoom (mouse): move the camera with the HIP only.
            cam = self.plotter.renderer.GetActiveCamera()
            offset = np.subtract(cam.GetPosition(), cam.GetFocalPoint())
            self._place_camera(self._last_hip, offset, cam.GetViewAngle())
        self.frames_shown += 1
        self.request_render()

    def show_control(self, snap: object | None, *, render: bool = False) -> None:
        """The constraint force at the HIP from a control snapshot (``force_n``, ``hip_m``): an
        arrow of :data:`FORCE_SCALE_M_PER_N` from the HIP sphere's surface outward (from its
        centre a few newtons stayed inside the sphere, over the fused normal), hidden below
        :data:`FORCE_MIN_N` or without a snapshot. Moves the one arrow actor; a paint only if
        ``render``."""
        if self._geometry is None:
            return
        force = np.asarray(getattr(snap, "force_n", (0.0, 0.0, 0.0)), dtype=np.float64)
        magnitude = float(np.linalg.norm(force)) if np.isfinite(force).all() else 0.0
        show = snap is not None and magnitude >= FORCE_MIN_N
        if show:
            length = min(FORCE_SCALE_M_PER_N * magnitude, FORCE_MAX_M)
            hip = np.asarray(snap.hip_m, dtype=np.float64)  # type: ignore[union-attr]
            start = hip + (self._geometry.r_hip_m / magnitude) * force
            # As thick as a 60 mm arrow however short: a few newtons stay readable.
            width = max(length, FORCE_MIN_WIDTH_M)
            self._move("force", _placement(start, force, length, width))
        self.force_n = magnitude if show else 0.0
        self._visible("force", show, "force")
        if render:
            self.request_render()

    def show_stopped(self, text: str = "STOPPED") -> None:
        """Show the stop banner at once (the source confirms with its next snapshot)."""
        if self._geometry is None:
            return
        self._stop_shown = True
        self._banner.SetInput(text)
        self._banner.SetVisibility(True)
        self.request_render()

    def show_markers(
        self,
        key: str,
        centroids: NDArray | None,
        normals: NDArray | None = None,
        colour: str = "#111111",
    ) -> None:
        """Extra estimates drawn as points with normals (a recording's re-run beside the
        recorded ones): ``(N, 3)`` centroids and unit normals, ``None`` or empty hides them.
        Two actors per ``key``, made on first use (a :meth:`set_geometry` removes them), then
        updated in place; part of the *camera estimates* layer. Schedules no paint."""
        if self._geometry is None:
            return
        points_name, lines_name = f"markers:{key}:points", f"markers:{key}:normals"
        if points_name not in self._actors:
            self._add(
                points_name,
                pv.PolyData(_EMPTY.copy()),
                "estimates",
                color=colour,
                point_size=11,
                render_points_as_spheres=True,
            )
            self._add(
                lines_name, pv.Line((0, 0, 0), (1, 0, 0)), "estimates", color=colour, line_width=3
            )
        pts = None if centroids is None else np.asarray(centroids, dtype=np.float64).reshape(-1, 3)
        shown = _set_cloud(self._meshes[points_name], pts)
        self._visible(points_name, shown, "estimates")
        lines = shown and normals is not None and len(normals) == len(pts)
        if lines:
            tips = pts + _ARROW_M * np.asarray(normals, dtype=np.float64).reshape(-1, 3)
            mesh = self._meshes[lines_name]
            mesh.points = np.vstack((pts, tips))
            n = len(pts)
            mesh.lines = np.column_stack((np.full(n, 2), np.arange(n), np.arange(n) + n)).ravel()
        self._visible(lines_name, bool(lines), "estimates")

    def _visible(self, name: str, has_data: bool, layer: str | None = None) -> None:
        self._has_data[name] = has_data
        on = self._layer_on[layer] if layer is not None else True
        self._actors[name].SetVisibility(has_data and on)

    def _show_robot(self, robot: Sequence[Primitive]) -> None:
        for i in range(len(self._geometry.robot_shapes) if self._geometry else 0):
            name = f"robot:{i}"
            if i >= len(robot):
                self._visible(name, False, "robot")
                continue
            prim = robot[i]
            if isinstance(prim, Sphere):
                self._move(name, _scaled_at(prim.center, prim.radius))
            elif isinstance(prim, Capsule):
                axis = prim.b - prim.a
                length = float(np.linalg.norm(axis))
                # To the micrometre (a link's length from the joint angles wobbles in its last
                # bits); a radius under a micrometre is drawn as one.
                dims = (round(length, 6), max(round(float(prim.radius), 6), 1e-6))
                if dims != self._capsule_dims.get(name):
                    self._capsule_dims[name] = dims
                    local = np.array(self._capsule.points)
                    local[self._capsule_upper, 2] += dims[0] / dims[1]
                    mesh = self._meshes[name]
                    mesh.points = local * dims[1]
                    mesh.point_data["Normals"] = self._capsule_normals
                u, v, w = _basis(axis if length > 1e-9 else np.array([0.0, 0.0, 1.0]))
                m = np.eye(4)
                m[:3, :3] = np.column_stack((u, v, w))
                m[:3, 3] = prim.a
                self._move(name, m)
            elif isinstance(prim, Box):
                m = np.eye(4)
                m[:3, :3] = prim.rotation * (2.0 * prim.half_extents)
                m[:3, 3] = prim.center
                self._move(name, m)
            self._visible(name, True, "robot")

    def _show_camera(self, frame: CameraFrame) -> None:
        est, name = frame.estimate, frame.name
        self._visible(
            f"context:{name}", _set_cloud(self._meshes[f"context:{name}"], frame.context), "context"
        )
        self._visible(
            f"cloud:{name}", _set_cloud(self._meshes[f"cloud:{name}"], est.points), "clouds"
        )
        self._visible(
            f"filled:{name}", _set_cloud(self._meshes[f"filled:{name}"], est.filled), "clouds"
        )
        # Points of the clusters stage C rejected: part of the by-stage picture only.
        rejected = est.rejected if self._color_mode == "stage" else None
        self._visible(
            f"rejected:{name}", _set_cloud(self._meshes[f"rejected:{name}"], rejected), "clouds"
        )
        if est.valid:
            self._move(f"centroid:{name}", _scaled_at(est.centroid, 0.005))
            self._move(f"normal:{name}", _placement(est.centroid, est.normal, _ARROW_M))
        self._visible(f"centroid:{name}", est.valid, "estimates")
        self._visible(f"normal:{name}", est.valid, "estimates")

    def _show_shells(self, snap: Snapshot) -> None:
        radii: list[float] = []
        circle_pts: list[FloatArray] = []
        circle_rgb: list[NDArray[np.uint8]] = []
        normal_pts: list[FloatArray] = []
        normal_rgb: list[NDArray[np.uint8]] = []
        hip = np.asarray(snap.hip)
        theta = np.linspace(0.0, 2.0 * math.pi, _CIRCLE_SEGMENTS + 1)
        ring = np.column_stack((np.cos(theta), np.sin(theta)))
        index = {cam.name: i for i, cam in enumerate(self._geometry.cameras)}  # type: ignore[union-attr]
        for frame in snap.cameras:
            colour = _hex_rgb(CAMERA_COLOURS[index.get(frame.name, 0) % len(CAMERA_COLOURS)])
            for shell in frame.estimate.shells:
                radii.append(shell.r_outer_m)
                if not shell.valid:
                    continue
                rgb = np.array(colour if shell.kept else REJECTED_GREY, np.uint8)
                u, v, w = _basis(shell.normal)
                if shell.kind == "circle" and shell.radius_m > 0:
                    radius = shell.radius_m
                else:
                    # A plane fit: draw where the plane cuts the shell's outer sphere.
                    depth = abs(float((hip - shell.center) @ w))
                    radius = math.sqrt(max(shell.r_outer_m**2 - depth**2, 0.0))
                circle_pts.append(shell.center + radius * (ring[:, :1] * u + ring[:, 1:] * v))
                circle_rgb.append(np.tile(rgb, (len(ring), 1)))
                normal_pts.append(np.vstack((shell.center, shell.center + _SHELL_NORMAL_M * w)))
                normal_rgb.append(np.tile(rgb, (2, 1)))

        unique = sorted({round(r, 4) for r in radii})
        sphere_mesh = self._meshes["shell_spheres"]
        if unique:
            template = _unit_sphere()
            n_template = template.n_points
            if len(unique) != self._shell_count:
                faces = template.faces.reshape(-1, 4)
                tiled = np.concatenate(
                    [
                        faces + np.array([0, k * n_template, k * n_template, k * n_template])
                        for k in range(len(unique))
                    ]
                )
                sphere_mesh.points = np.zeros((n_template * len(unique), 3))
                sphere_mesh.faces = tiled.ravel()
                self._shell_count = len(unique)
            base = np.asarray(template.points)
            sphere_mesh.points = np.concatenate([hip + r * base for r in unique])
        self._visible("shell_spheres", bool(unique), "shells")
        self._set_lines("shell_circles", circle_pts, circle_rgb, closed=False)
        self._set_lines("shell_normals", normal_pts, normal_rgb, closed=False)

    def _set_lines(
        self,
        name: str,
        polylines: list[FloatArray],
        colours: list[NDArray[np.uint8]],
        *,
        closed: bool,
    ) -> None:
        mesh = self._meshes[name]
        if not polylines:
            self._visible(name, False, "shells")
            return
        points = np.concatenate(polylines)
        cells: list[int] = []
        start = 0
        for line in polylines:
            cells.append(len(line))
            cells.extend(range(start, start + len(line)))
            start += len(line)
        mesh.points = points
        mesh.lines = np.asarray(cells, dtype=np.int64)
        mesh.point_data.set_array(np.concatenate(colours), "rgb")
        self._visible(name, True, "shells")

    def _show_fused(self, snap: Snapshot) -> None:
        fused = snap.fused
        # Nothing stale is drawn: past the age the tick stops trusting it (the status bar
        # says how old the newest estimate is), the fused marker goes.
        ok = fused is not None and fused.valid and fused.age_s <= FUSED_SHOWN_MAX_AGE_S
        if ok:
            self._move("fused_centroid", _scaled_at(fused.centroid, 0.007))
            self._move("fused_normal", _placement(fused.centroid, fused.normal, 1.3 * _ARROW_M))
            gap = self._meshes["gap"]
            gap.points = np.vstack((snap.hip, fused.centroid))
        for name in ("fused_centroid", "fused_normal", "gap"):
            self._visible(name, ok, "fused")

    def _show_truth(self, snap: Snapshot) -> None:
        truth = snap.truth
        ok = truth is not None
        if ok:
            self._move("truth_point", _scaled_at(truth.point, 0.004))
            self._move("truth_normal", _placement(truth.point, truth.normal, _ARROW_M))
        self._visible("truth_point", ok, "truth")
        self._visible("truth_normal", ok, "truth")

    # ----- images -------------------------------------------------------------------------------
    def image(self) -> NDArray[np.uint8]:
        """The 3D view rendered now as the widget shows it, ``(H, W, 3)`` uint8 in device pixels
        (for screenshots and tests): VTK's frame stretched like the paint stretches it."""
        from .screenshot import qimage_from_rgb, qimage_to_array

        rgb = self.canvas.frame()
        ratio = self.canvas.devicePixelRatioF()
        w, h = round(self.canvas.width() * ratio), round(self.canvas.height() * ratio)
        if rgb.shape[:2] == (h, w):
            return rgb
        smooth = QtCore.Qt.TransformationMode.SmoothTransformation
        stretched = qimage_from_rgb(rgb).scaled(
            w, h, QtCore.Qt.AspectRatioMode.IgnoreAspectRatio, smooth
        )
        return qimage_to_array(stretched)

    def close_view(self) -> None:
        """Release the VTK render window (call before the widget is destroyed)."""
        self.canvas.release()


def _blend(colour: str, other: str, amount: float) -> str:
    a, b = np.array(_hex_rgb(colour)), np.array(_hex_rgb(other))
    mixed = np.round((1 - amount) * a + amount * b).astype(int)
    return "#" + "".join(f"{c:02x}" for c in mixed)

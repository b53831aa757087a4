"""The robot's links in the 3D view: each capsule drawn where the session's link is, moved by its
actor's matrix, its mesh rebuilt only when the link's length or radius changes."""

from __future__ import annotations

import numpy as np
from hapticloud.app.scene_view import SceneView
from hapticloud.core.geometry.primitives import Capsule, Sphere
from hapticloud.hardware.live.contract import SceneGeometry

GEOMETRY = SceneGeometry(
    name="links", cameras=(), bodies=(), r_hip_m=0.04, robot_shapes=("sphere", "capsule")
)


def _aabb(capsule: Capsule) -> np.ndarray:
    lo = np.minimum(capsule.a, capsule.b) - capsule.radius
    hi = np.maximum(capsule.a, capsule.b) + capsule.radius
    return np.column_stack((lo, hi)).ravel()  # VTK's (xmin, xmax, ymin, ymax, zmin, zmax)


def _shown_bounds(view: SceneView, capsule: Capsule) -> np.ndarray:
    """The world box of the link's drawn vertices: its mesh placed by its actor's matrix."""
    view._show_robot((Sphere(np.zeros(3), 0.04), capsule))
    matrix = view._actors["robot:1"].GetUserMatrix()
    m = np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])
    world = np.array(view._meshes["robot:1"].points) @ m[:3, :3].T + m[:3, 3]
    return np.column_stack((world.min(axis=0), world.max(axis=0))).ravel()


def test_a_link_is_drawn_where_it_is_and_moving_it_does_not_rebuild_its_mesh(qtbot) -> None:
    view = SceneView()
    qtbot.addWidget(view, before_close_func=lambda v: v.close_view())
    view.set_geometry(GEOMETRY)
    mesh = view._meshes["robot:1"]
    # Tessellated with 16 steps: the mesh lies within 2 % of the radius inside the true surface.
    tol = 0.02 * 0.03 + 1e-9

    first = Capsule([0.1, -0.2, 0.9], [0.25, -0.1, 1.05], 0.03)
    np.testing.assert_allclose(_shown_bounds(view, first), _aabb(first), atol=tol)
    built = np.array(mesh.points)

    # The same link elsewhere, turned (same length, radius): only its matrix changes.
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    moved = Capsule(turn @ first.a + [0.3, 0.0, 0.1], turn @ first.b + [0.3, 0.0, 0.1], 0.03)
    np.testing.assert_allclose(_shown_bounds(view, moved), _aabb(moved), atol=tol)
    np.testing.assert_array_equal(np.array(mesh.points), built)

    # A longer link is rebuilt to its new length.
    longer = Capsule(first.a, first.a + 2.0 * (first.b - first.a), 0.03)
    np.testing.assert_allclose(_shown_bounds(view, longer), _aabb(longer), atol=tol)
    assert not np.array_equal(np.array(mesh.points), built)

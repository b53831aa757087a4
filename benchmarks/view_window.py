"""The 3D view in a window of the app's size: frames per second and CPU per frame.

The :class:`~hapticloud.app.scene_view.SceneView` of a checkout is put in a 1440x900 window
beside a panel of labels and a table (one label and the status bar change every frame, as the
app's session panel and status bar do), fed ``hapticloud bench gui``'s synthetic snapshots as
fast as it paints, for ``--seconds`` after a warm-up. Prints one JSON line: paints per second,
process CPU per paint (ms; llvmpipe renders on two threads), wall time per paint, view size.

Side by side with another commit (its checkout needs the packages it declared, e.g. pyvistaqt
for commits before the off-screen canvas)::

    git worktree add /tmp/base <rev>
    xvfb-run -a -s "-screen 0 1440x900x24" .venv/bin/python benchmarks/view_window.py --at /tmp/base
    xvfb-run -a -s "-screen 0 1440x900x24" .venv/bin/python benchmarks/view_window.py
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--at", type=Path, default=None, help="checkout to measure (default: this)")
    parser.add_argument("--seconds", type=float, default=8.0)
    args = parser.parse_args()
    if args.at is not None:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from run_at import _point_the_install_at

        _point_the_install_at(args.at.resolve())

    from hapticloud.app import scene_view
    from hapticloud.app.bench_gui import _Frames
    from PyQt6 import QtWidgets

    app = QtWidgets.QApplication(sys.argv[:1])
    frames = _Frames()
    window = QtWidgets.QMainWindow()
    central = QtWidgets.QWidget()
    layout = QtWidgets.QHBoxLayout(central)
    view = scene_view.SceneView()
    layout.addWidget(view, 3)
    side = QtWidgets.QWidget()
    side_layout = QtWidgets.QVBoxLayout(side)
    labels = [QtWidgets.QLabel(f"label {i}") for i in range(12)]
    for label in labels:
        side_layout.addWidget(label)
    side_layout.addWidget(QtWidgets.QTableWidget(10, 3))
    layout.addWidget(side, 1)
    window.setCentralWidget(central)
    window.resize(1440, 900)
    window.show()
    view.set_geometry(frames.geometry)
    for key in ("clouds", "bodies", "truth", "robot", "shells", "estimates", "fused"):
        view.set_layer_visible(key, True, render=False)

    paints = [0]
    widget = getattr(view, "canvas", None)
    if widget is not None:
        widget.on_paint.append(lambda a, b: paints.__setitem__(0, paints[0] + 1))
    else:  # before the canvas: pyvistaqt's QOpenGLWidget, counted in its paintGL
        paint_gl = view.plotter.paintGL

        def counted() -> None:
            paint_gl()
            paints[0] += 1

        view.plotter.paintGL = counted
    warm = time.perf_counter() + 1.5
    while time.perf_counter() < warm:
        app.processEvents()

    k = 0
    first, cpu0, t0 = paints[0], time.process_time(), time.perf_counter()
    while time.perf_counter() - t0 < args.seconds:
        want = paints[0] + 1
        view.show_snapshot(frames.snapshot(0.033 * k))
        labels[k % len(labels)].setText(f"value {k} {time.perf_counter():.3f}")
        window.statusBar().showMessage(f"frame {k}")
        while paints[0] < want:
            app.processEvents()
        k += 1
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    n = paints[0] - first
    print(
        json.dumps(
            {
                "checkout": str(args.at or "."),
                "fps": round(n / wall, 1),
                "cpu_ms_per_frame": round(1e3 * cpu / n, 1),
                "wall_ms_per_frame": round(1e3 * wall / n, 1),
                "view_px": [view.width(), view.height()],
            }
        ),
        flush=True,
    )
    view.close_view()
    window.close()
    app.processEvents()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

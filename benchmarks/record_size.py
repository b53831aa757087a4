"""Recording size and the recorder's CPU: frames stored as their workspace ROI or whole.

Runs SCENE (deterministic, ``--duration`` s) twice with the recorder on its frame hook, once per
``record.frames`` mode, and prints each file's size and the recorder process's CPU time.

    .venv/bin/python benchmarks/record_size.py --scene sliding --duration 5
"""

from __future__ import annotations

import argparse
import os
import tempfile

from hapticloud.core.recording import RecordConfig
from hapticloud.core.scene import load_scene
from hapticloud.core.studies.run import run_scene
from hapticloud.hardware.recording.recorder import Recorder, config_tomls
from hapticloud.hardware.recording.runs import frame_hook


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="sliding")
    parser.add_argument("--duration", type=float, default=5.0)
    args = parser.parse_args()
    scene = load_scene(args.scene)
    cfg = scene.config
    sizes = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ("roi", "full"):
            path = os.path.join(tmp, f"{mode}.mcap")
            recorder = Recorder(
                path,
                {"source": "benchmarks/record_size.py"},
                config_tomls(cfg.perception, cfg.fusion),
                record=RecordConfig(frames=mode),
                crop=cfg.perception.crop,
            )
            recorder.wait_ready()
            recorder.sink.blocking = True  # a simulated run: wait, never drop
            run_scene(scene, None, args.duration, frame_sink=frame_hook(recorder.sink))
            result = recorder.close()
            sizes[mode] = os.path.getsize(path)
            print(
                f"{mode:4s}: {sizes[mode] / 1e6:6.2f} MB for {args.duration:g} s "
                f"({sizes[mode] / 1e6 / args.duration:.2f} MB/s), recorder CPU "
                f"{result['cpu_s']:.2f} s"
            )
    print(f"full / roi: {sizes['full'] / sizes['roi']:.1f}x")


if __name__ == "__main__":
    main()

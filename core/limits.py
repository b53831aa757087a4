"""Bounds shared by the core and the command line (a module light enough for ``--help``).

- :data:`MAX_DURATION_S`: the longest run of a scene, ``scene.duration_s`` in a scene file and
  ``--duration`` of ``hapticloud run`` and ``bench loop``. A run keeps every 800 Hz tick in
  memory (the simulator's record, the control process's log), so an unbounded duration is a
  MemoryError, not a long run.
- :data:`BENCH_FRAMES_MIN`, :data:`BENCH_FRAMES_MAX`: frames per scene of ``bench perception``:
  at least one approach/leave segment of its HIP track, at most about an hour of study
  (~0.6 s a frame).
"""

MAX_DURATION_S = 600.0
BENCH_FRAMES_MIN = 15
BENCH_FRAMES_MAX = 5000

__all__ = ["BENCH_FRAMES_MAX", "BENCH_FRAMES_MIN", "MAX_DURATION_S"]

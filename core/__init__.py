"""hapticloud.core: the algorithms.

Pure Python with numpy, scipy, Open3D and Pinocchio. No Qt, no threads, no device I/O: everything
here is deterministic given its inputs and testable headless.
"""

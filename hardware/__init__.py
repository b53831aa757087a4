"""hapticloud.hardware: everything that talks to the outside in real time.

- :mod:`hapticloud.hardware.drives`: the CAN FD drive protocol, master link, emulator and fault
  injection;
- :mod:`hapticloud.hardware.sources`: camera sources behind ``read(timeout)`` / ``close()``;
- :mod:`hapticloud.hardware.session`: the session state machine and the staged watchdogs;
- :mod:`hapticloud.hardware.control`: the 800 Hz control process and its bus benchmark.

No Qt here; this layer may import :mod:`hapticloud.core`, never :mod:`hapticloud.app`.
"""

"""hapticloud.hardware: everything that talks to the outside in real time.

The drive bus (:mod:`hapticloud.hardware.drives`: protocol, master link, emulator, fault
injection), and later the control process, camera sources and sessions. No Qt here; this layer
may import :mod:`hapticloud.core`, never :mod:`hapticloud.app`.
"""

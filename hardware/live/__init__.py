"""The live data path the app shows, run off the GUI: processes and threads, no Qt.

* :mod:`.contract`: what the window reads and asks (snapshots, source state, the tunable
  :class:`~.contract.LiveConfig`); the app imports these and nothing that runs.
* :mod:`.scenes`: the simulated scenes and their static geometry.
* :mod:`.worker`: the worker (sim cameras -> perception -> fusion, and a running control
  process's estimates), one packet per camera frame.
* :mod:`.source`: :class:`~.source.LiveSource`, the supervisor that runs the worker in its own
  process and turns packets into snapshots on a receiver thread.
* :mod:`.session`: :class:`~.session.Session`, the control process's handle and telemetry.
"""

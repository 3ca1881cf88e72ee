"""Live observation sources for onboard flight (cameras behind the Observation interface).

:class:`~onfly.sources.camera.CameraFeed` runs any observation stream on a thread and keeps its
newest frame; :func:`~onfly.sources.camera.open_camera` opens one from a spec (a simulated
vehicle's ``tcp://`` camera, a recording played at real time, or ``realsense``).
:mod:`onfly.sources.realsense` (optional extra) is imported only when used.
"""

from onfly.sources.camera import CameraError, CameraFeed, PolledSource, open_camera

__all__ = ["CameraError", "CameraFeed", "PolledSource", "open_camera"]

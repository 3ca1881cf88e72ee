"""The one set of defaults shared by the Python API, the ``onfly`` CLI and the benchmark.

Everything that flies an episode in the embedded world (:func:`onfly.fly`, ``onfly run``,
``onfly bench`` / ``onfly sweep`` and :class:`onfly.bench.episode.EpisodeConfig`) takes its
defaults from here, so a script that keeps the defaults runs the settings the CLI and the
benchmark run. This module imports nothing heavy (the CLI reads it at start-up).

Sources: the episode protocol (70 s limit, 10 Hz control, 5 m success radius) is the paper's
("Simulation Experimental Setup"); the camera (320 x 214 px, 90 x 60 deg, a frame every 0.5 s)
is the setting measured to let the CPU ray caster fly ~10x realtime (see
``experiments/configs/quick.toml``).
"""

from __future__ import annotations

__all__ = [
    "TIME_LIMIT_S",
    "CONTROL_PERIOD_S",
    "FRAME_PERIOD_S",
    "SUCCESS_RADIUS_M",
    "WIDTH_PX",
    "HEIGHT_PX",
    "HFOV_DEG",
    "VFOV_DEG",
    "RENDER_THREADS",
    "VLM",
    "METHOD",
    "SEED",
    "WORLD",
]

TIME_LIMIT_S = 70.0
CONTROL_PERIOD_S = 0.1
FRAME_PERIOD_S = 0.5
SUCCESS_RADIUS_M = 5.0

WIDTH_PX = 320
HEIGHT_PX = 214
HFOV_DEG = 90.0
VFOV_DEG = 60.0
RENDER_THREADS = 1

VLM = "sim:nominal"
METHOD = "onfly"
SEED = 0

#: The ``[world]`` table of a benchmark config with nothing set.
WORLD = {
    "width_px": WIDTH_PX,
    "height_px": HEIGHT_PX,
    "hfov_deg": HFOV_DEG,
    "vfov_deg": VFOV_DEG,
    "render_threads": RENDER_THREADS,
}

"""Rerun recordings: camera, depth, map, plans, goals and the agents' words on one timeline.

Entity layout (world ENU, metres; timeline ``sim_time`` in seconds):

- ``world/camera`` (pinhole, posed) with ``world/camera/rgb`` and ``world/camera/depth``;
  2D markers on the image: ``.../history_point``, ``.../vlm_pixel``, ``.../refined_pixel``
- ``world/map/occupied`` occupied ESDF voxels (every ``map_every`` frames)
- ``world/vehicle`` position, ``world/path/executed`` flown path, ``world/path/planned`` plan
- ``world/goal/raw`` the VLM pixel lifted at its own depth, ``world/goal/verified`` the goal
  the planner got
- ``log/agents`` decisions, monitoring statuses, memory contents, task events (text)
- ``metrics/...`` scalar time series (e.g. ``onfly replay``'s clearance, slack and latency
  per frame), one entity per name

Recordings are written to an ``.rrd`` file (``rerun rrd verify FILE`` checks one; ``rerun FILE``
opens it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr

from onfly.observation import Observation
from planning.frames import quat_from_matrix
from planning.trajectory import Trajectory, VehicleState

__all__ = ["RerunRecorder"]


class RerunRecorder:
    """Writes one recording to ``path``. Context manager; :meth:`close` flushes the file."""

    def __init__(self, path: str | Path, application_id: str = "onfly", map_every: int = 5) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream(application_id)
        self.rec.save(str(self.path))
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.map_every = max(1, int(map_every))
        self._frames = 0
        self._executed: list[np.ndarray] = []
        self._events_seen = 0
        self._camera = None

    def __enter__(self) -> "RerunRecorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()

    def _time(self, t_s: float) -> None:
        self.rec.set_time("sim_time", duration=float(t_s))

    def log_frame(self, obs: Observation) -> None:
        """Camera pose, intrinsics, RGB and depth of one frame."""
        self._time(obs.t_s)
        cam = obs.camera
        q = quat_from_matrix(obs.T_world_cam[:3, :3])  # (w, x, y, z)
        self.rec.log(
            "world/camera",
            rr.Transform3D(translation=obs.T_world_cam[:3, 3], quaternion=[q[1], q[2], q[3], q[0]]),
        )
        if self._camera != cam:
            self.rec.log(
                "world/camera",
                rr.Pinhole(image_from_camera=cam.K, resolution=[cam.width, cam.height], camera_xyz=rr.ViewCoordinates.RDF),
                static=True,
            )
            self._camera = cam
        self.rec.log("world/camera/rgb", rr.Image(obs.rgb))
        depth = np.nan_to_num(obs.depth_m, nan=0.0, posinf=0.0, neginf=0.0)
        self.rec.log("world/camera/depth", rr.DepthImage(depth, meter=1.0))
        self._frames += 1

    def log_map(self, t_s: float, occupied_points: np.ndarray, force: bool = False) -> None:
        """Occupied voxels (n, 3); logged every ``map_every`` frames unless ``force``."""
        if not force and self._frames % self.map_every != 0:
            return
        self._time(t_s)
        self.rec.log("world/map/occupied", rr.Points3D(np.asarray(occupied_points, float), radii=0.05, colors=[150, 150, 160]))

    def log_state(self, state: VehicleState) -> None:
        self._time(state.t_s)
        self._executed.append(state.p.copy())
        self.rec.log("world/vehicle", rr.Points3D([state.p], radii=0.25, colors=[255, 200, 0]))
        if len(self._executed) >= 2:
            self.rec.log("world/path/executed", rr.LineStrips3D([np.array(self._executed)], colors=[255, 200, 0]))

    def log_plan(self, t_s: float, trajectory: Trajectory) -> None:
        self._time(t_s)
        self.rec.log("world/path/planned", rr.LineStrips3D([trajectory.p], colors=[0, 200, 255]))

    def log_goal(self, t_s: float, name: str, goal_world, color=(0, 255, 0)) -> None:
        self._time(t_s)
        if goal_world is None:
            self.rec.log(f"world/goal/{name}", rr.Clear(recursive=False))
        else:
            self.rec.log(f"world/goal/{name}", rr.Points3D([np.asarray(goal_world, float)], radii=0.3, colors=[color]))

    def log_pixel(self, t_s: float, name: str, uv, color=(255, 0, 0)) -> None:
        self._time(t_s)
        if uv is None:
            self.rec.log(f"world/camera/rgb/{name}", rr.Clear(recursive=False))
        else:
            self.rec.log(f"world/camera/rgb/{name}", rr.Points2D([uv], radii=6, colors=[color]))

    def log_text(self, t_s: float, text: str, level: str = "INFO") -> None:
        self._time(t_s)
        self.rec.log("log/agents", rr.TextLog(text, level=level))

    def log_scalars(self, t_s: float, values) -> None:
        """Scalar time series: ``{name: value}`` logged at ``metrics/<name>``; non-finite
        values are skipped (a plot gap, not a spike)."""
        self._time(t_s)
        for name, value in values.items():
            v = float(value)
            if np.isfinite(v):
                self.rec.log(f"metrics/{name}", rr.Scalars(v))

    def log_pilot_events(self, events) -> None:
        """Log the pilot events not yet logged (``onfly.pilot.PilotEvent`` list)."""
        for ev in events[self._events_seen :]:
            d = ev.data
            if ev.kind == "decision":
                self.log_pixel(ev.t_s, "history_point", d.get("history_uv"), (255, 255, 0))
                self.log_pixel(ev.t_s, "vlm_pixel", d.get("pixel"), (255, 0, 0))
                ver = d.get("verifier") or {}
                self.log_pixel(ev.t_s, "refined_pixel", ver.get("refined_uv"), (0, 255, 0))
                if d.get("goal_world") is not None:
                    self.log_goal(ev.t_s, "verified", d["goal_world"])
                status = "ok" if d.get("goal_world") is not None else f"no goal ({d.get('reason')})"
                self.log_text(ev.t_s, f"decision [{d.get('subtask')}] raw={d.get('raw')!r} -> {status}")
            elif ev.kind == "monitor":
                self.log_text(
                    ev.t_s,
                    f"monitor [{d.get('subtask')}] {d.get('status')} raw={d.get('raw')!r} memory={d.get('memory')}",
                    level="INFO" if d.get("status") else "WARN",
                )
            else:
                self.log_text(ev.t_s, f"{ev.kind}: {d}", level="WARN" if ev.kind in ("lost", "goal_timeout", "agent_error") else "INFO")
        self._events_seen = len(events)

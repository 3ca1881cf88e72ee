"""The task manager: a queue of subtasks advanced by the monitoring agent's status.

The instruction is decomposed once when it arrives (``vlm.decompose``); the manager then
holds the current subtask, counts consecutive STOPs (a *stable* STOP advances), ends the
episode on the last subtask's stable STOP, and records the last *normal* point (the pose at
the most recent CONTINUE) that LOST recovery turns back to.

One recovery per normal point (ours; the paper says only "stop, then reorient to the heading of
the last normal point"): a LOST after which no CONTINUE has given a new normal point, and the
subtask has not advanced, changes nothing. Turning again to the heading the vehicle has already
turned to cannot help, and in closed loop a monitor that keeps answering LOST (the target was
seen earlier in the memory, not now) otherwise stops the vehicle every monitoring period and
starves navigation for the rest of the episode.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

__all__ = ["Status", "TaskEvent", "TaskManager", "TaskManagerError", "same_subtask"]


def _subtask_key(text: str) -> str:
    return " ".join(text.split()).rstrip(" .!?;,").casefold()


def same_subtask(a: str | None, b: str | None) -> bool:
    """Whether two subtask texts are the same step, up to case, spacing and closing
    punctuation: a decomposition may return "Fly to the yellow car" for the instruction
    "Fly to the yellow car.", and an answer about one is an answer about the other."""
    if a is None or b is None:
        return a is b
    return _subtask_key(a) == _subtask_key(b)


class TaskManagerError(ValueError):
    """Invalid subtask list or status."""


class Status(str, Enum):
    """The monitoring agent's forced-choice output."""

    CONTINUE = "CONTINUE"
    STOP = "STOP"
    LOST = "LOST"


class TaskEvent(str, Enum):
    """What a status did to the task."""

    NONE = "none"  # CONTINUE, a STOP not yet stable, or a LOST with no new normal point
    ADVANCED = "advanced"  # stable STOP on a non-final subtask: the next one is current
    FINISHED = "finished"  # stable STOP on the last subtask: the episode ends
    LOST = "lost"  # recovery: stop, turn to the last normal heading, resume


@dataclass(frozen=True)
class _NormalPoint:
    t_s: float
    position: np.ndarray
    yaw: float


class TaskManager:
    """Holds the subtask queue and turns statuses into task events.

    Parameters
    ----------
    subtasks : non-empty ordered list of non-empty strings
    stop_confirmations : consecutive STOPs that make a STOP stable (1 = act on the first)
    intermediate_confirmations : consecutive STOPs that advance past a subtask that is not the
        last (None = ``stop_confirmations``). The costs are not the same: a false STOP on the
        last subtask ends the task where it is, a false STOP on an earlier one only starts the
        next subtask early, and each confirmation costs a monitoring call (1-2 s) per subtask
    """

    def __init__(self, subtasks: list[str], stop_confirmations: int = 2, intermediate_confirmations: int | None = None) -> None:
        subtasks = [s.strip() for s in subtasks]
        if not subtasks or any(not s for s in subtasks):
            raise TaskManagerError(f"subtasks must be a non-empty list of non-empty strings, got {subtasks!r}")
        if stop_confirmations < 1:
            raise TaskManagerError(f"stop_confirmations must be >= 1, got {stop_confirmations}")
        if intermediate_confirmations is not None and intermediate_confirmations < 1:
            raise TaskManagerError(f"intermediate_confirmations must be >= 1, got {intermediate_confirmations}")
        self.subtasks = subtasks
        self.stop_confirmations = stop_confirmations
        self.intermediate_confirmations = stop_confirmations if intermediate_confirmations is None else intermediate_confirmations
        self.index = 0
        self.finished = False
        self._stops = 0
        self.last_normal: _NormalPoint | None = None
        self._recovered = False  # a recovery was started since the last normal point / advance
        self.history: list[tuple[float, int, Status, TaskEvent]] = []

    @property
    def current(self) -> str:
        """The current subtask (the last one once finished)."""
        return self.subtasks[min(self.index, len(self.subtasks) - 1)]

    def with_next(self, n: int) -> str:
        """The current subtask with the next ``n`` subtasks as its later steps, one text
        (``"Fly along the aisle, then stop beside the whiteboard"``): the form in which the
        prompts read a subtask of several steps (the target is the last step's object). The
        current subtask alone when ``n`` is 0 or it is the last."""
        if n < 0:
            raise TaskManagerError(f"n must be >= 0, got {n}")
        steps = self.subtasks[min(self.index, len(self.subtasks) - 1) :][: n + 1]
        text = steps[0].strip().rstrip(".").rstrip()
        for step in steps[1:]:
            step = step.strip().rstrip(".").rstrip()
            text += ", then " + step[:1].lower() + step[1:]
        return text if len(steps) > 1 else steps[0]

    @property
    def pending_stops(self) -> int:
        """Consecutive STOPs heard on the current subtask that are not yet stable (0 after any
        other status)."""
        return self._stops

    @property
    def is_last(self) -> bool:
        return self.index == len(self.subtasks) - 1

    def on_status(self, status: Status | str, t_s: float, position, yaw: float, joined: bool = False) -> TaskEvent:
        """Feed one monitoring status observed at ``t_s`` with the body pose at that time.

        ``joined``: the status judged the current subtask with the next as its later step
        (:meth:`with_next`), so a STOP says the *next* subtask's target is reached. It advances
        past the current one; when the next is the last, it also counts as the first of the
        last's confirmations (the monitor would only be asked the same question again).
        """
        status = Status(status)
        if self.finished:
            return TaskEvent.NONE
        event = TaskEvent.NONE
        if status is Status.CONTINUE:
            self._stops = 0
            self._recovered = False
            self.last_normal = _NormalPoint(float(t_s), np.asarray(position, float).copy(), float(yaw))
        elif status is Status.STOP:
            self._stops += 1
            if self._stops >= (self.stop_confirmations if self.is_last else self.intermediate_confirmations):
                self._stops = 0
                if self.is_last:
                    self.finished = True
                    event = TaskEvent.FINISHED
                else:
                    self.index += 1
                    # a normal point belongs to its subtask: recovery never turns back
                    # toward the previous subtask's target
                    self.last_normal = None
                    self._recovered = False
                    event = TaskEvent.ADVANCED
                    if joined and self.is_last:
                        self._stops = 1
                        if self._stops >= self.stop_confirmations:
                            self._stops = 0
                            self.finished = True
                            event = TaskEvent.FINISHED
        else:
            self._stops = 0
            if not self._recovered:  # one recovery per normal point (module docstring)
                self._recovered = True
                event = TaskEvent.LOST
        self.history.append((float(t_s), self.index, status, event))
        return event

    def recovery_yaw(self, fallback_yaw: float) -> float:
        """Heading to turn to after LOST: the last normal point's, else ``fallback_yaw``."""
        return self.last_normal.yaw if self.last_normal is not None else float(fallback_yaw)

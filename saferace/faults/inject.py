"""The faults of :mod:`.spec` applied to one episode's frames, odometry and commands.

A :class:`FaultInjector` sees the true frame and velocities of every step and gives out
what the faulty sensors would; it sees the driver's (or the filter's) command and gives
out what the faulty actuators apply. The camera's stream is built in order: latency picks
an older true frame, a dropped frame repeats the last one given out, a frozen camera
repeats the last one given out before it froze; then the image itself is blacked out,
occluded or flickers.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from saferace.faults.spec import Fault

#: Added to the episode's seed for the faults' generator, so that their draws never
#: repeat the scene's own.
FAULT_SEED_SALT = 0x5AFE


class FaultInjector:
    """Applies ``faults`` to an episode, commands held to ``action_low .. action_high``
    (see the module)."""

    def __init__(
        self,
        faults: tuple[Fault, ...],
        action_low: np.ndarray,
        action_high: np.ndarray,
    ) -> None:
        self.faults = {fault.name: fault for fault in faults}
        self.action_low = np.asarray(action_low, np.float32)
        self.action_high = np.asarray(action_high, np.float32)
        latency = self.faults.get("latency")
        self._history = 1 + (int(latency["steps"]) if latency else 0)
        self.reset(None)

    def reset(self, seed: int | None) -> None:
        """Start an episode; ``seed`` (the episode's) fixes every random draw."""
        entropy = None if seed is None else [int(seed), FAULT_SEED_SALT]
        self.rng = np.random.default_rng(entropy)
        self._frames: deque[np.ndarray] = deque(maxlen=self._history)
        self._given: np.ndarray | None = None  # the last frame given out
        self._frozen: np.ndarray | None = None
        delay = self.faults.get("delay")
        self._commands: deque[np.ndarray] = deque(
            [np.zeros(2, np.float32)] * (int(delay["steps"]) if delay else 0)
        )
        self._patch_corner = self.rng.random(2)  # the occlusion's place, per episode
        self._noise = np.zeros(3)  # the odometry's noise this step, of [v_x, v_y, r]

    def active(self, time_s: float) -> list[str]:
        """The faults acting at ``time_s`` after the reset, by name."""
        return [name for name, fault in self.faults.items() if fault.active(time_s)]

    def _acting(self, name: str, time_s: float) -> Fault | None:
        fault = self.faults.get(name)
        return fault if fault is not None and fault.active(time_s) else None

    def frame(self, image: np.ndarray, time_s: float) -> np.ndarray:
        """The frame the faulty camera gives out at ``time_s``, the true one ``image``."""
        self._frames.append(image)
        latency = self._acting("latency", time_s)
        late = 0
        if latency is not None:
            steps = int(latency["steps"])
            late = int(self.rng.integers(0, steps + 1)) if latency["random"] else steps
        stream = self._frames[-1 - min(late, len(self._frames) - 1)]
        dropped = self._acting("dropped", time_s)
        if (
            dropped is not None
            and self._given is not None
            and self.rng.random() < dropped["probability"]
        ):
            stream = self._given
        if self._acting("frozen", time_s) is not None:
            if self._frozen is None:
                self._frozen = stream if self._given is None else self._given
            stream = self._frozen
        else:
            self._frozen = None
        self._given = stream
        return self._looks(stream.copy(), time_s)  # a frame given twice is two arrays

    def _looks(self, image: np.ndarray, time_s: float) -> np.ndarray:
        """``image`` (changed in place) blacked out, occluded or flickering, where those
        faults act."""
        if self._acting("blackout", time_s) is not None:
            image[:] = 0
            return image
        occlusion = self._acting("occlusion", time_s)
        flicker = self._acting("flicker", time_s)
        if occlusion is not None:
            height, width = image.shape[:2]
            side = math.sqrt(occlusion["fraction"])
            rows, columns = round(side * height), round(side * width)
            top = int(self._patch_corner[0] * (height - rows + 1))
            left = int(self._patch_corner[1] * (width - columns + 1))
            image[top : top + rows, left : left + columns] = 0
        if flicker is not None:
            gain = 1.0 + flicker["amplitude"] * self.rng.uniform(-1.0, 1.0)
            image = np.clip(image.astype(np.float32) * gain, 0, 255).astype(np.uint8)
        return image

    def velocity(self, velocity: np.ndarray, time_s: float) -> np.ndarray:
        """``[v_x, v_y, r]`` as the faulty odometry measures the true ``velocity``."""
        odometry = self._acting("odometry", time_s)
        if odometry is None:
            return velocity
        scale = np.array([1.0 + odometry["bias"], 1.0, 1.0 + odometry["bias"]])
        self._noise = self.rng.normal(0.0, odometry["noise"], 3)
        return (velocity * scale + self._noise).astype(velocity.dtype)

    def odometry(self, step: np.ndarray, dt_s: float, time_s: float) -> np.ndarray:
        """The body-frame move ``(dx, dy, dyaw)`` the faulty odometry measures over a
        control step of ``dt_s`` ending at ``time_s``, the true move ``step``: off as
        :meth:`velocity` (called first, for the same step) read the speed and the yaw rate,
        its noise integrated over the step: one sensor, read twice."""
        odometry = self._acting("odometry", time_s)
        if odometry is None:
            return step
        scale = np.array([1.0 + odometry["bias"], 1.0, 1.0 + odometry["bias"]])
        return step * scale + self._noise * dt_s

    def command(self, action: np.ndarray, time_s: float) -> np.ndarray:
        """What the faulty actuators apply for ``action`` given at ``time_s``."""
        applied = np.asarray(action, np.float32)
        delay = self.faults.get("delay")
        if delay is not None:
            self._commands.append(applied)
            late = self._commands.popleft()
            applied = late if delay.active(time_s) else applied
        steering = self._acting("steering", time_s)
        if steering is not None:
            applied = applied + np.array([steering["offset"], 0.0], np.float32)
        return np.clip(applied, self.action_low, self.action_high)

"""Rerun recordings (``.rrd``) of episodes, for visual debugging.

Entities: ``camera/*`` onboard images; ``map/*`` a top-down map (y up) with the lane
boundaries, the center and racing lines, the car's position over time and its whole
path at the end; ``plots/*`` speed, reference speed, steering and lateral offsets over
the ``sim_time`` timeline. In traffic also ``map/opponents`` (each opponent's position,
labelled) and ``events/collisions`` (a line per collision: the cars, the one at fault, the
kind and the relative speed). Behind a safety filter also ``filter/*``: the state the filter
believed (the mean of its state source's samples and a band of two spreads) against the
truth for ``e_y``, ``e_psi`` and ``kappa``, the nominal and filtered steering and
acceleration, and the barrier values.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from saferace.track import Track
from saferace.track.raceline import ReferenceLine

_MAP_FLIP = np.array([1.0, -1.0])  # Rerun's 2D views have y down; maps read better with y up


def _map_points(xy: np.ndarray | tuple[float, float]) -> np.ndarray:
    return np.asarray(xy) * _MAP_FLIP


class EpisodeRecording:
    """Logs one episode to a Rerun recording saved at ``path``."""

    def __init__(
        self, path: str | Path, track: Track, lines: list[ReferenceLine], stereo: bool = False
    ) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.stream = rr.RecordingStream("saferace")
        self.stream.save(self.path)
        self.stereo = stereo
        self._path_xy: list[tuple[float, float]] = []
        left, right = track.boundaries(0.1)
        log = self.stream.log
        log(
            "map/lane_boundaries",
            rr.LineStrips2D(
                [_map_points(np.vstack([b, b[:1]])) for b in (left, right)],
                colors=[[230, 230, 230]],
                radii=0.02,
            ),
            static=True,
        )
        colours = {"center": [150, 150, 150], "racing": [180, 60, 220]}
        for line in lines:
            xy = line.path.position(line.s_m)
            log(
                f"map/{line.name}_line",
                rr.LineStrips2D(
                    [_map_points(np.vstack([xy, xy[:1]]))],
                    colors=[colours.get(line.name, [0, 160, 255])],
                    radii=0.015,
                ),
                static=True,
            )

    def log_step(
        self, observation: dict[str, np.ndarray], info: dict[str, Any], action: np.ndarray
    ) -> None:
        """One control step: camera image(s), car position, and the scalar plots."""
        stream = self.stream
        stream.set_time("sim_time", duration=info["time_s"])
        image = observation["image"]
        if self.stereo:
            stream.log("camera/left", rr.Image(image[..., :3]))
            stream.log("camera/right", rr.Image(image[..., 3:]))
        else:
            stream.log("camera/onboard", rr.Image(image))
        position = (info["x_m"], info["y_m"])
        self._path_xy.append(position)
        stream.log(
            "map/car", rr.Points2D([_map_points(position)], colors=[[255, 60, 60]], radii=0.08)
        )
        for name, value in (
            ("plots/speed_mps", info["v_x_mps"]),
            ("plots/ref_speed_mps", info["ref_speed_mps"]),
            ("plots/steer_rad", float(action[0])),
            ("plots/accel_cmd_mps2", float(action[1])),
            ("plots/e_y_m", info["e_y_m"]),
            ("plots/deviation_m", info["deviation_m"]),
        ):
            stream.log(name, rr.Scalars(value))
        opponents = info.get("opponents", ())
        if opponents:
            stream.log(
                "map/opponents",
                rr.Points2D(
                    [_map_points((o["x_m"], o["y_m"])) for o in opponents],
                    colors=[[60, 110, 255]],
                    radii=0.08,
                    labels=[o["name"] for o in opponents],
                ),
            )
        for collision in info.get("collisions", ()):
            cars = " and ".join(collision["cars"])
            text = (
                f"{cars} collide ({collision['kind']}, "
                f"{collision['relative_speed_mps']:.2f} m/s): {collision['at_fault']} at fault"
            )
            stream.log("events/collisions", rr.TextLog(text, level="WARN"))
        if "safety" in info:
            self._log_filter(info)

    def _log_filter(self, info: dict[str, Any]) -> None:
        safety, log = info["safety"], self.stream.log
        for index, name in enumerate(("e_y_m", "e_psi_rad", "kappa_radpm")):
            mean, spread = safety["state_mean"][index], safety["state_std"][index]
            log(f"filter/{name}/true", rr.Scalars(safety["state_true"][index]))
            log(f"filter/{name}/believed", rr.Scalars(mean))
            log(f"filter/{name}/believed_minus_2sd", rr.Scalars(mean - 2.0 * spread))
            log(f"filter/{name}/believed_plus_2sd", rr.Scalars(mean + 2.0 * spread))
        for index, name in enumerate(("steer_rad", "accel_mps2")):
            log(f"filter/{name}/nominal", rr.Scalars(safety["nominal_action"][index]))
            log(f"filter/{name}/filtered", rr.Scalars(safety["filtered_action"][index]))
        for name, value in safety["barriers"].items():
            log(f"filter/barriers/{name}", rr.Scalars(value))

    def close(self) -> None:
        """Log the whole driven path and write the file."""
        if self._path_xy:
            self.stream.log(
                "map/driven_path",
                rr.LineStrips2D(
                    [_map_points(np.asarray(self._path_xy))], colors=[[255, 120, 0]], radii=0.02
                ),
                static=True,
            )
        self.stream.flush()
        self.stream.disconnect()

"""The filter's backup plan and its check (a gatekeeper): an action is sent only if, after
it, braking back onto the reference line keeps the car inside its lane.

The lane barriers look at the lane where the car is now. Where the lane bends within a
few metres (Monza's chicane swings its curvature from +0.8 to -0.7 1/m in 3 m of a 2.2 m
lane) a barrier with a slow gain pushes the car off the racing line, which crosses the
chicane nearly straight, and the car then meets a bend at 7 m/s that the tyres' grip
cannot follow from where it is. A check that looks ahead catches that in time: each step
the filter's action is driven forward one control period on the kinematic bicycle in the
lane's frame, then the backup plan (steer back towards the reference line within the
tyres' grip, brake to a stop) to a standstill. If the car stays inside the lane all the
way the action is sent; otherwise the backup's own first action is, where the backup
from now holds (Gurriet et al. 2018's backup set; Agrawal and Panagou's gatekeeper).

The plan is a model: it ignores sliding and opponents (the car barriers keep to those).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from saferace.track.raceline import ReferenceLine
from saferace.track.track import Track

#: Braking of the backup plan (m/s^2): firm, with the friction ellipse's rest for turning.
BACKUP_BRAKE_MPS2 = 3.0
#: The friction circle the backup brakes within (m/s^2; the tyres give about 9.8), and its
#: least braking, where the turn takes it all.
FRICTION_MPS2 = 8.0
TYRE_GRIP_MPS2 = 9.8
MIN_BRAKE_MPS2 = 0.5
#: Lateral acceleration the backup steers within (m/s^2), as the speed limit's corners.
BACKUP_LATERAL_MPS2 = 7.0
#: The margin (m) an action's plan keeps beyond the backup's own: the backup takes over
#: while its plan still holds with that much to spare, not at its last chance.
CHECK_MARGIN_M = 0.04
#: Room (m) an action's plan may keep less than the backup's, where that is below the
#: margin: an action that speeds up for one period comes out of its plan a little worse.
TIE_M = 0.01
#: How far ahead the backup aims at the reference line (s), and its least distance (m).
LOOKAHEAD_S = 0.3
MIN_LOOKAHEAD_M = 0.8
#: Steps of the plan per control period: at 7 m/s one period covers a third of a metre.
SUBSTEPS = 2
#: Below this speed the plan has stopped (m/s).
STOPPED_MPS = 0.05
#: Spacing of the map's samples the plan reads (m).
GRID_M = 0.05


@dataclass(frozen=True)
class PlanState:
    """The car in the lane's frame: ``s_m`` along the centre line, offset ``e_y_m``,
    heading ``e_psi_rad`` to the centre line, speed ``v_mps`` and the wheels' angle."""

    s_m: float
    e_y_m: float
    e_psi_rad: float
    v_mps: float
    steer_rad: float


class BackupPlan:
    """Braking back onto ``reference`` within the tyres' grip, driven on the kinematic
    bicycle of ``wheelbase_m`` whose wheels follow commands with ``steer_time_constant_s``
    (up to ``max_steer_rad``), and whether it keeps a car ``half_width_m`` wide (half)
    inside ``track``'s lane."""

    def __init__(
        self,
        track: Track,
        reference: ReferenceLine,
        wheelbase_m: float,
        steer_time_constant_s: float,
        max_steer_rad: float,
        half_width_m: float,
        control_dt_s: float,
    ) -> None:
        self.length_m = track.length_m
        grid = np.arange(0.0, track.length_m, GRID_M)
        right, left = track.widths(grid)
        self.kappa = track.centerline.curvature(grid).tolist()
        self.w_left = np.asarray(left, dtype=float).tolist()
        self.w_right = np.asarray(right, dtype=float).tolist()
        self.line = np.asarray(reference.offset_at(grid), dtype=float).tolist()
        self.wheelbase_m = wheelbase_m
        self.max_steer_rad = max_steer_rad
        self.half_width_m = half_width_m
        self.dt_s = control_dt_s / SUBSTEPS
        self.steer_follow = 1.0 - math.exp(-self.dt_s / max(steer_time_constant_s, 1e-6))

    def _at(self, s_m: float) -> int:
        return round((s_m % self.length_m) / GRID_M) % len(self.kappa)

    def steer(self, state: PlanState) -> float:
        """The backup's steering: the lane's curvature where the car is, plus pure pursuit
        of the reference line ``LOOKAHEAD_S`` ahead, within the grip and the wheels' reach."""
        return self._steer(state.s_m, state.e_y_m, state.e_psi_rad, state.v_mps)

    def _steer(self, s_m: float, e_y_m: float, e_psi_rad: float, v_mps: float) -> float:
        lookahead_m = max(MIN_LOOKAHEAD_M, LOOKAHEAD_S * v_mps)
        kappa = self.kappa[self._at(s_m)]
        target = self.line[self._at(s_m + lookahead_m)]
        aim = math.atan2(target - e_y_m, lookahead_m) - e_psi_rad
        curvature = kappa / max(1.0 - kappa * e_y_m, 0.05) + 2.0 * math.sin(aim) / lookahead_m
        grip = BACKUP_LATERAL_MPS2 / max(v_mps, 0.5) ** 2
        steer = math.atan(self.wheelbase_m * min(max(curvature, -grip), grip))
        return min(max(steer, -self.max_steer_rad), self.max_steer_rad)

    def brake_mps2(self, v_mps: float, steer_rad: float) -> float:
        """The backup's braking at speed ``v_mps`` turning at ``steer_rad``: what the friction
        circle leaves beside the turn, at most ``BACKUP_BRAKE_MPS2`` (braking hard in a
        turn at the grip spins this car: its rear brakes take 40% of the braking)."""
        lateral = min(v_mps**2 * abs(math.tan(steer_rad)) / self.wheelbase_m, FRICTION_MPS2)
        return min(BACKUP_BRAKE_MPS2, max(MIN_BRAKE_MPS2, math.sqrt(FRICTION_MPS2**2 - lateral**2)))

    def clearance(
        self, state: PlanState, first: tuple[float, float] | None, spread_m: float
    ) -> float:
        """The least room (m) the car keeps to its lane's edges after ``first`` (steering,
        acceleration; ``None``: the backup from now) for one control period and the backup
        after it, to a standstill, with ``spread_m`` of doubt about its offset: negative
        where it leaves."""
        s, e_y, e_psi, v, wheels = (
            state.s_m, state.e_y_m, state.e_psi_rad, state.v_mps, state.steer_rad,
        )  # fmt: skip
        margin, dt, follow, wheelbase = (
            self.half_width_m + spread_m, self.dt_s, self.steer_follow, self.wheelbase_m,
        )  # fmt: skip
        curvatures, lefts, rights = self.kappa, self.w_left, self.w_right
        least, step, i = math.inf, 0, self._at(s)
        while v > STOPPED_MPS:
            if first is not None and step < SUBSTEPS:
                command, accel = first
            else:
                command, accel = self._steer(s, e_y, e_psi, v), -self.brake_mps2(v, wheels)
            wheels += (command - wheels) * follow
            kappa = curvatures[self._at(s + 0.5 * v * dt)]  # mid-step: chicanes turn in 0.3 m
            s_dot = v * math.cos(e_psi) / max(1.0 - kappa * e_y, 0.05)
            s += s_dot * dt
            e_y += v * math.sin(e_psi) * dt
            grip = BACKUP_LATERAL_MPS2 / max(v, 0.5) ** 2  # turning harder slides
            turn = min(max(math.tan(wheels) / wheelbase, -grip), grip)
            e_psi += (v * turn - kappa * s_dot) * dt
            v = max(0.0, v + accel * dt)
            i = self._at(s)
            least = min(least, lefts[i] - e_y - margin, rights[i] + e_y - margin)
            step += 1
        return least

    def instead(self, state: PlanState, action: np.ndarray, spread_m: float) -> np.ndarray | None:
        """The backup's action ``[steer_rad, accel_mps2]`` where ``action``'s plan keeps less
        room than the backup's from now (up to ``CHECK_MARGIN_M``, less ``TIE_M``), or where
        it brakes in a turn beyond the tyres' grip; ``None`` where it keeps as much: the
        action is then as safe as the plan can tell."""
        steer, accel = float(action[0]), float(action[1])
        lateral = state.v_mps**2 * abs(math.tan(steer)) / self.wheelbase_m
        if accel >= 0.0 or math.hypot(lateral, accel) <= TYRE_GRIP_MPS2:
            kept = self.clearance(state, (steer, accel), spread_m)
            if (
                kept >= CHECK_MARGIN_M - TIE_M
                or kept >= self.clearance(state, None, spread_m) - TIE_M
            ):
                return None
        return np.array([self.steer(state), -self.brake_mps2(state.v_mps, state.steer_rad)])

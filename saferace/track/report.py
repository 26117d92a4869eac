"""What a user wants to know about a track before driving it: ``saferace track-info``.

Length, lane width range, the tightest turn, where the loader narrowed the lane so that no
boundary folds, how far smoothing moved the centre line, and what the minimum-curvature
racing line gains over the centre line (its integral of kappa^2 ds and the estimated lap
times of both, from the same speed profile).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from saferace.errors import SafeRaceError
from saferace.track.raceline import RacingLineSettings, ReferenceLine, center_line, racing_line
from saferace.track.smoothing import SmoothingKeeps
from saferace.track.track import Track, builtin_track_names
from saferace.track.vehicle_envelope import VehicleEnvelope


@dataclass(frozen=True)
class TrackReport:
    """A track's numbers and its two reference lines."""

    track: Track
    center: ReferenceLine
    racing: ReferenceLine

    @property
    def lane_width_range_m(self) -> tuple[float, float]:
        return lane_width_range_m(self.track)

    def rows(self) -> list[list]:
        """``[quantity, value]`` rows of the report."""
        track, center, racing = self.track, self.center, self.racing
        narrowest, widest = self.lane_width_range_m
        kappa_gain = 1.0 - racing.curvature_squared_integral / center.curvature_squared_integral
        rows: list[list] = []
        if track.smoothing:
            rows += [
                ["smoothed lane keeps the given", track.smoothing.keeps],
                ["centre line smoothed: most moved [m]", track.smoothing.max_shift_m],
                ["centre line smoothed: RMS moved [m]", track.smoothing.rms_shift_m],
            ]
        return [
            *rows,
            ["length [m]", track.length_m],
            ["points", track.point_count],
            ["lane width [m]", f"{narrowest:.3f} - {widest:.3f}"],
            ["tightest centre-line radius [m]", track.min_turn_radius_m()],
            ["points narrowed (turns tighter than the half width)", track.narrowing.points],
            ["most narrowed [m]", track.narrowing.max_m],
            ["int kappa^2 ds, centre line [1/m]", center.curvature_squared_integral],
            ["int kappa^2 ds, racing line [1/m]", racing.curvature_squared_integral],
            ["racing line: less kappa^2 [%]", 100.0 * kappa_gain],
            ["estimated lap, centre line [s]", center.lap_time_s],
            ["estimated lap, racing line [s]", racing.lap_time_s],
            ["racing line: faster by [%]", 100.0 * (1.0 - racing.lap_time_s / center.lap_time_s)],
            ["top speed, racing line [m/s]", float(np.max(racing.vx_mps))],
        ]


def lane_width_range_m(track: Track) -> tuple[float, float]:
    """The narrowest and widest lane of ``track`` over its points."""
    w_right, w_left = track.widths(track.centerline.knot_s_m[:-1])
    width = w_right + w_left
    return float(width.min()), float(width.max())


def builtin_track_rows() -> list[list]:
    """``[name, length, lane width, tightest radius]`` of every built-in track."""
    rows = []
    for name in builtin_track_names():
        track = Track.load(name)
        narrowest, widest = lane_width_range_m(track)
        width = (
            f"{narrowest:.2f}" if widest - narrowest < 0.005 else f"{narrowest:.2f}-{widest:.2f}"
        )
        rows.append([name, f"{track.length_m:.1f}", width, f"{track.min_turn_radius_m():.2f}"])
    return rows


def track_report(
    track: Track,
    envelope: VehicleEnvelope | None = None,
    settings: RacingLineSettings | None = None,
) -> TrackReport:
    """Both reference lines of ``track`` and the numbers that describe it."""
    envelope = envelope or VehicleEnvelope()
    settings = settings or RacingLineSettings()
    return TrackReport(
        track, center_line(track, envelope, settings.step_m), racing_line(track, envelope, settings)
    )


def load_track_report(
    track: str,
    car_width_m: float | None = None,
    margin_m: float | None = None,
    strict: bool = False,
    smooth_rms_m: float | None = None,
    smooth_keeps: SmoothingKeeps | None = None,
) -> TrackReport:
    """Load ``track`` (a built-in name or a CSV) for a car ``car_width_m`` wide, smoothed by
    ``smooth_rms_m`` keeping ``smooth_keeps``, and report on it with a racing line kept
    ``margin_m`` from the edges (None: the defaults)."""
    if smooth_keeps and smooth_rms_m is None:
        raise SafeRaceError("smooth_keeps says what a smoothed lane keeps: add smooth_rms_m")
    envelope = VehicleEnvelope()
    if car_width_m is not None:
        if car_width_m <= 0:
            raise SafeRaceError(f"car_width_m must be positive, got {car_width_m}")
        envelope = replace(envelope, width_m=car_width_m)
    settings = RacingLineSettings()
    if margin_m is not None:
        if margin_m < 0:
            raise SafeRaceError(f"margin_m must not be negative, got {margin_m}")
        settings = replace(settings, margin_m=margin_m)
    loaded = Track.load(
        track,
        car_width_m=envelope.width_m,
        strict=strict,
        smooth_rms_m=smooth_rms_m,
        smooth_keeps=smooth_keeps or "widths",
    )
    return track_report(loaded, envelope, settings)

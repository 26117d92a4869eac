"""A racing track: a closed centerline with left and right lane widths.

Load one by name (``Track.load("lab")``), from a CSV file (``Track.load("my.csv")``)
or from arrays (``Track.from_arrays(...)``). Every constructor validates the lane
and raises :class:`~saferace.errors.TrackError` with the offending row.
"""

from __future__ import annotations

import functools
import hashlib
import logging
from importlib import resources
from pathlib import Path
from typing import overload

import numpy as np

from saferace.errors import TrackError
from saferace.track import validation
from saferace.track.frenet import FrenetProjector
from saferace.track.path import ClosedPath
from saferace.track.periodic import PeriodicInterpolator
from saferace.track.smoothing import Smoothing, SmoothingKeeps, smooth_centerline
from saferace.track.track_io import read_track_csv, write_track_csv
from saferace.track.vehicle_envelope import VehicleEnvelope

LOG = logging.getLogger(__name__)
#: Narrowings already warned about in this process (a table loads its track on every run).
_REPORTED_NARROWINGS: set[tuple] = set()
TRACKS_PACKAGE = "saferace.assets.tracks"
#: Samples used to check the boundaries for crossings, at most.
_MAX_CHECK_SAMPLES = 2000
_CHECK_STEP_M = 0.1


def builtin_track_names() -> list[str]:
    """Names of the tracks shipped in ``saferace/assets/tracks``."""
    folder = resources.files(TRACKS_PACKAGE)
    return sorted(p.name[:-4] for p in folder.iterdir() if p.name.endswith(".csv"))


def builtin_track_path(name: str) -> Path:
    """Path of a built-in track's CSV file."""
    return Path(str(resources.files(TRACKS_PACKAGE).joinpath(f"{name}.csv")))


class Track:
    """A validated closed lane: centerline :class:`ClosedPath` plus widths along it.

    ``s`` is the centerline arc length in metres, starting at the first point of the
    file and increasing in the order of the points. ``e_y`` is positive to the left.
    ``narrowing`` says where the loader narrowed the lane so that no boundary folds,
    ``smoothing`` how far a smoothed centre line moved (None: as given).
    """

    def __init__(
        self,
        name: str,
        centerline: ClosedPath,
        w_right_m: np.ndarray,
        w_left_m: np.ndarray,
        narrowing: validation.Narrowing = validation.NOT_NARROWED,
        smoothing: Smoothing | None = None,
    ) -> None:
        self.name = name
        self.centerline = centerline
        self.narrowing = narrowing
        self.smoothing = smoothing
        self._point_s = centerline.point_s_m
        self._w_right = PeriodicInterpolator(self._point_s, w_right_m, centerline.length_m)
        self._w_left = PeriodicInterpolator(self._point_s, w_left_m, centerline.length_m)

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(
        cls,
        name_or_path: str | Path,
        car_width_m: float = VehicleEnvelope.width_m,
        strict: bool = False,
        smooth_rms_m: float | None = None,
        smooth_keeps: SmoothingKeeps = "widths",
    ) -> Track:
        """A built-in track by name, or a track CSV by path (``strict``, ``smooth_rms_m``,
        ``smooth_keeps``: see :meth:`from_arrays`)."""
        text = str(name_or_path)
        load_csv = functools.partial(
            cls.from_csv,
            car_width_m=car_width_m,
            strict=strict,
            smooth_rms_m=smooth_rms_m,
            smooth_keeps=smooth_keeps,
        )
        if text in builtin_track_names():
            return load_csv(builtin_track_path(text), name=text)
        path = Path(text)
        if path.suffix.lower() == ".csv" or path.exists():
            return load_csv(path)
        raise TrackError(
            f"unknown track {text!r}: give a CSV path or one of {', '.join(builtin_track_names())}"
        )

    @classmethod
    def from_csv(
        cls,
        path: str | Path,
        car_width_m: float = VehicleEnvelope.width_m,
        name: str | None = None,
        strict: bool = False,
        smooth_rms_m: float | None = None,
        smooth_keeps: SmoothingKeeps = "widths",
    ) -> Track:
        """Read and validate a track file (see :mod:`saferace.track.track_io`)."""
        table = read_track_csv(path)
        lines = table.line_numbers

        def row(i: int) -> str:
            return f"line {lines[i]}"  # the file is named once, before the whole message

        try:
            return cls.from_arrays(
                table.x_m,
                table.y_m,
                table.w_right_m,
                table.w_left_m,
                name=name or Path(path).stem,
                car_width_m=car_width_m,
                row_name=row,
                strict=strict,
                smooth_rms_m=smooth_rms_m,
                smooth_keeps=smooth_keeps,
            )
        except TrackError as exc:
            message = str(exc)
            if not message.startswith(str(path)):
                message = f"{path}: {message}"
            raise TrackError(message) from None

    @classmethod
    def from_arrays(
        cls,
        x_m: np.ndarray,
        y_m: np.ndarray,
        w_right_m: np.ndarray | float,
        w_left_m: np.ndarray | float,
        name: str = "custom",
        car_width_m: float = VehicleEnvelope.width_m,
        row_name: validation.RowName = validation.default_row_name,
        strict: bool = False,
        smooth_rms_m: float | None = None,
        smooth_keeps: SmoothingKeeps = "widths",
    ) -> Track:
        """Build and validate a track from centerline points and widths (scalars broadcast).

        ``smooth_rms_m``: replace a noisy centre line by a smoothing spline that passes
        this RMS distance from the points, keeping the given widths (the boundaries move
        with the centre line) or, ``smooth_keeps="boundaries"``, the given boundaries
        (:func:`~saferace.track.smoothing.smooth_centerline`; off by default). Where a turn is
        tighter than its inner half width, the lane is narrowed there so that the boundary
        does not fold (:func:`~saferace.track.validation.narrow_folding_widths`), and where
        two legs of the track come closer than the lane is wide, both are clipped to keep
        to their side of the line between them
        (:func:`~saferace.track.validation.clip_meeting_legs`); one warning per process says
        how much. ``strict=True`` refuses such a track instead.
        """
        x_m = np.asarray(x_m, dtype=float).ravel()
        y_m = np.asarray(y_m, dtype=float).ravel()
        w_right_m = np.broadcast_to(np.asarray(w_right_m, dtype=float), x_m.shape).copy()
        w_left_m = np.broadcast_to(np.asarray(w_left_m, dtype=float), x_m.shape).copy()
        if len(x_m) > 1 and np.hypot(x_m[-1] - x_m[0], y_m[-1] - y_m[0]) < 1e-6:
            x_m, y_m, w_right_m, w_left_m = x_m[:-1], y_m[:-1], w_right_m[:-1], w_left_m[:-1]
        validation.check_points(x_m, y_m, w_right_m, w_left_m, row_name)
        smoothing = None
        if smooth_rms_m is not None:
            lane = smooth_centerline(x_m, y_m, w_right_m, w_left_m, smooth_rms_m, smooth_keeps)
            x_m, y_m, w_right_m, w_left_m = lane.x_m, lane.y_m, lane.w_right_m, lane.w_left_m
            smoothing = lane.smoothing
        centerline = ClosedPath(np.column_stack([x_m, y_m]))
        _check_centerline(centerline, row_name)  # before narrowing, which would hide it
        narrowing = validation.NOT_NARROWED
        if not strict:
            given = w_right_m, w_left_m
            w_right_m, w_left_m = _narrowed_widths(centerline, w_right_m, w_left_m)
            narrowing = validation.Narrowing.between(*given, w_right_m, w_left_m)
            reported = (name, len(x_m), narrowing.points, round(narrowing.max_m, 6))
            if narrowing.points:
                LOG.log(
                    logging.DEBUG if reported in _REPORTED_NARROWINGS else logging.WARNING,
                    "%s: narrowed the lane at %d of %d points, by up to %.3f m, where turns are "
                    "tighter than the half width or two legs of the track come closer than the "
                    "lane is wide (Track.load(..., strict=True) refuses instead)",
                    name,
                    narrowing.points,
                    len(x_m),
                    narrowing.max_m,
                )
                _REPORTED_NARROWINGS.add(reported)
        validation.check_lane_width(w_right_m, w_left_m, car_width_m, row_name, narrowing)
        track = cls(name, centerline, w_right_m, w_left_m, narrowing, smoothing)
        track._validate_geometry(row_name)
        return track

    def _validate_geometry(self, row_name: validation.RowName) -> None:
        s = self.centerline.sample(_check_step_m(self.centerline))
        rows = self.row_of(s)

        def row_of_sample(i: int) -> str:
            return row_name(int(rows[i]))

        w_right, w_left = self.widths(s)
        dense_s = self.centerline.knot_s_m[:-1]
        dense_right, dense_left = self.widths(dense_s)
        validation.check_turn_radius(
            self.centerline.curvature(dense_s),
            dense_right,
            dense_left,
            lambda i: row_name(int(self.row_of(dense_s[i]))),
        )
        center = self.centerline.position(s)
        normal = self.centerline.normal(s)
        left = center + w_left[:, None] * normal
        right = center - w_right[:, None] * normal
        validation.check_no_self_intersection("left boundary", left, row_of_sample)
        validation.check_no_self_intersection("right boundary", right, row_of_sample)

    # ---------------------------------------------------------------- geometry
    @property
    def length_m(self) -> float:
        """Centerline length of one lap."""
        return self.centerline.length_m

    @property
    def point_s_m(self) -> np.ndarray:
        """Centerline arc length of each point the track was given with."""
        return self._point_s

    @property
    def point_count(self) -> int:
        """Number of centerline points the track was given with."""
        return len(self._point_s)

    def row_of(self, s_m: np.ndarray) -> np.ndarray:
        """Index of the input point at or before each arc length (for error messages)."""
        return np.searchsorted(self._point_s, self.centerline.wrap(s_m), side="right") - 1

    @overload
    def widths(self, s_m: float) -> tuple[float, float]: ...
    @overload
    def widths(self, s_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    @overload
    def widths(self, s_m: np.ndarray | float) -> tuple[np.ndarray | float, np.ndarray | float]: ...
    def widths(self, s_m: np.ndarray | float) -> tuple[np.ndarray | float, np.ndarray | float]:
        """Right and left lane half widths at ``s`` (linear between the input points)."""
        return self._w_right(s_m), self._w_left(s_m)

    @functools.cached_property
    def fingerprint(self) -> str:
        """SHA-256 of the lane as loaded (points and widths): equal for equal geometry."""
        x_m, y_m = self.centerline.position(self._point_s).T
        lane = np.column_stack([x_m, y_m, *self.widths(self._point_s)])
        return hashlib.sha256(np.ascontiguousarray(lane).tobytes()).hexdigest()

    def to_csv(self, path: str | Path) -> None:
        """Write the lane as loaded (smoothed, narrowed) at its points, in the CSV format it
        is read from."""
        x_m, y_m = self.centerline.position(self._point_s).T
        w_right_m, w_left_m = self.widths(self._point_s)
        write_track_csv(path, x_m, y_m, w_right_m, w_left_m)

    def boundaries(self, step_m: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
        """Left and right boundary polylines ``(n, 2)`` sampled every ``step_m``."""
        return self.boundaries_at(self.centerline.sample(step_m))

    def boundaries_at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Left and right boundary points ``(n, 2)`` at centerline arc lengths ``s``."""
        center, normal = self.centerline.position(s), self.centerline.normal(s)
        w_right, w_left = self.widths(s)
        return center + w_left[:, None] * normal, center - w_right[:, None] * normal

    def min_turn_radius_m(self) -> float:
        """Smallest centerline turn radius."""
        kappa = self.centerline.curvature(self.centerline.knot_s_m[:-1])
        return float(1.0 / np.max(np.abs(kappa)))

    def projector(self) -> FrenetProjector:
        """A new stateful Frenet projector onto the centerline."""
        return FrenetProjector(self.centerline)

    def __repr__(self) -> str:
        return f"Track({self.name!r}, length_m={self.length_m:.2f}, points={self.point_count})"


def _check_step_m(centerline: ClosedPath) -> float:
    """Spacing of the samples the boundaries are checked at (and legs clipped)."""
    return max(_CHECK_STEP_M, centerline.length_m / _MAX_CHECK_SAMPLES)


def _check_centerline(centerline: ClosedPath, row_name: validation.RowName) -> None:
    """The centre line must not cross itself."""
    s = centerline.sample(_check_step_m(centerline))
    rows = np.searchsorted(centerline.point_s_m, s, side="right") - 1
    validation.check_no_self_intersection(
        "center line", centerline.position(s), lambda i: row_name(int(rows[i]))
    )


def _narrowed_widths(
    centerline: ClosedPath, w_right_m: np.ndarray, w_left_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The half widths narrowed where turns fold the inner boundary, then clipped where two
    legs of the track meet (see :meth:`Track.from_arrays`)."""
    point_s = centerline.point_s_m
    distance = validation.arc_distance(point_s, point_s, centerline.length_m)

    def segment_of(s_m: np.ndarray) -> np.ndarray:
        return np.searchsorted(centerline.point_s_m, s_m, side="right") - 1

    knots = centerline.knot_s_m[:-1]
    w_right_m, w_left_m = validation.narrow_folding_widths(
        centerline.curvature(knots), segment_of(knots), distance, w_right_m, w_left_m
    )
    samples = centerline.sample(_check_step_m(centerline))
    right_limit, left_limit = validation.meeting_leg_limits(
        centerline.position(samples), centerline.normal(samples), samples, centerline.length_m
    )
    return validation.clip_meeting_legs(
        right_limit, left_limit, segment_of(samples), distance, w_right_m, w_left_m
    )

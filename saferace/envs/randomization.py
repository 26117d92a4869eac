"""Typed ranges of the tasks' domain randomisation, with named presets.

:class:`VisualRandomization` changes how the scene looks (light, colours, textures, lane
markings, roadside objects, camera mounting, image noise); :class:`PhysicsRandomization`
changes the car (mass, tyre friction, motor strength), kept apart because it also changes
what the expert's and the filter's models assume. Each field is a closed range
``(low, high)`` drawn uniformly once per reset (a probability for yes/no choices); a
range ``(x, x)`` keeps that value as built (any visual randomisation builds the
randomizable scene, whose lines are not emissive: they dim with the light).
``RacingEnv(randomize=..., physics_randomize=...)`` takes a preset name (``none``,
``mild``, ``strong``; for the looks also a shift severity ``severity-0`` .. ``severity-5``)
or an instance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import TypeVar

from saferace.errors import SafeRaceError

Range = tuple[float, float]
PRESET_NAMES = ("none", "mild", "strong")


class RandomizationError(SafeRaceError, ValueError):
    """A randomisation range or preset that cannot be used."""


def _checked_range(name: str, value: Range, low: float, high: float) -> Range:
    """``value`` as a tuple of floats, if it is a non-empty range of finite numbers within
    ``[low, high]`` (a list is accepted: the fields stay hashable tuples)."""
    if not (isinstance(value, tuple | list) and len(value) == 2):
        raise RandomizationError(f"{name} must be a (low, high) pair, got {value!r}")
    lower, upper = value
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in (lower, upper)):
        raise RandomizationError(f"{name} must hold two finite numbers, got {value!r}")
    if lower > upper:
        raise RandomizationError(f"{name} is an empty range: low {lower} > high {upper}")
    if not low <= lower <= upper <= high:
        raise RandomizationError(f"{name} must lie within [{low}, {high}], got {value!r}")
    return float(lower), float(upper)


def _check_probability(name: str, value: float) -> None:
    if not (isinstance(value, int | float) and 0.0 <= value <= 1.0):
        raise RandomizationError(f"{name} must be a probability in [0, 1], got {value!r}")


_VISUAL_LIMITS = {
    "light_azimuth_rad": (-math.pi, math.pi),
    "light_elevation_rad": (-0.9, 0.3),
    "light_intensity": (0.0, 3.0),
    "line_width_scale": (0.1, 2.0),
    "line_fade": (0.0, 1.0),
    "line_wear": (0.0, 1.0),
    "camera_height_m": (-0.05, 0.1),
    "camera_pitch_rad": (-0.3, 0.3),
    "camera_fovy_deg": (-40.0, 40.0),
    "image_noise_std": (0.0, 100.0),
    "image_blur_sigma_px": (0.0, 10.0),
}


def _field_limits(name: str) -> Range:
    """What a range of :class:`VisualRandomization` may span."""
    if name.endswith("_tint"):
        return 0.0, 1.0
    if name.endswith(("_brightness", "_contrast")):
        return 0.0, 3.0 if "brightness" in name else 1.0
    return _VISUAL_LIMITS[name]


@dataclass(frozen=True)
class VisualRandomization:
    """How much the look of the scene varies between episodes (identity by default).

    Colours are scaled (``*_brightness``) and tinted (``*_tint``: each RGB channel times
    ``1 + U(-tint, tint)``); ``asphalt_texture_contrast`` is the amplitude of a per-episode
    noise texture on the asphalt (0 plain, 1 from black to the colour), which a look has
    with ``asphalt_textured_probability`` (sampling a texture costs a software rasteriser
    about 8% of a 64x64 step, so plain asphalt is drawn untextured). Dashed lines have
    0.5 m dashes and gaps.
    """

    light_azimuth_rad: Range = (0.0, 0.0)  # the sun turned about the vertical
    light_elevation_rad: Range = (0.0, 0.0)  # added to the sun's 70 deg elevation
    light_intensity: Range = (1.0, 1.0)  # scale of the sun's and the headlight's light
    light_tint: Range = (0.0, 0.0)
    asphalt_brightness: Range = (1.0, 1.0)
    asphalt_tint: Range = (0.0, 0.0)
    asphalt_texture_contrast: Range = (0.0, 0.0)
    asphalt_textured_probability: float = 1.0
    ground_brightness: Range = (1.0, 1.0)
    ground_tint: Range = (0.0, 0.0)
    sky_brightness: Range = (1.0, 1.0)
    sky_tint: Range = (0.0, 0.0)
    line_width_scale: Range = (1.0, 1.0)  # of the 0.07 m boundary lines
    line_fade: Range = (0.0, 0.0)  # share of the asphalt's colour mixed into the lines
    line_wear: Range = (0.0, 0.0)  # share of the lines' vertices worn to 0-50% width
    line_dashed_probability: float = 0.0
    roadside_hidden_probability: float = 0.0  # per kind of object (cones, boxes, posts)
    roadside_tint: Range = (0.0, 0.0)
    opponent_tint: Range = (0.0, 0.0)  # each opponent car's body colour
    camera_height_m: Range = (0.0, 0.0)  # added to the onboard cameras' 0.10 m
    camera_pitch_rad: Range = (0.0, 0.0)  # positive looks further down
    camera_fovy_deg: Range = (0.0, 0.0)  # added to the onboard cameras' 90 deg
    image_noise_std: Range = (0.0, 0.0)  # Gaussian pixel noise, in 8-bit levels
    image_blur_sigma_px: Range = (0.0, 0.0)  # Gaussian blur

    def __post_init__(self) -> None:
        for field in fields(self):
            name, value = field.name, getattr(self, field.name)
            if name.endswith("_probability"):
                _check_probability(name, value)
                continue
            object.__setattr__(self, name, _checked_range(name, value, *_field_limits(name)))

    @property
    def is_identity(self) -> bool:
        """Whether every draw gives the scene as built."""
        return self == VisualRandomization()


@dataclass(frozen=True)
class PhysicsRandomization:
    """How much the car varies between episodes (identity by default): scales of the
    chassis' mass and inertia, of the tyres' sliding friction and of the motors' torque."""

    mass_scale: Range = (1.0, 1.0)
    friction_scale: Range = (1.0, 1.0)
    motor_scale: Range = (1.0, 1.0)

    def __post_init__(self) -> None:
        for field in fields(self):
            value = _checked_range(field.name, getattr(self, field.name), 0.2, 5.0)
            object.__setattr__(self, field.name, value)

    @property
    def is_identity(self) -> bool:
        return self == PhysicsRandomization()


VISUAL_PRESETS: dict[str, VisualRandomization] = {
    "none": VisualRandomization(),
    "mild": VisualRandomization(
        light_azimuth_rad=(-0.8, 0.8),
        light_elevation_rad=(-0.3, 0.1),
        light_intensity=(0.75, 1.25),
        light_tint=(0.0, 0.08),
        asphalt_brightness=(0.8, 1.2),
        asphalt_tint=(0.0, 0.05),
        ground_brightness=(0.8, 1.2),
        ground_tint=(0.0, 0.1),
        sky_brightness=(0.85, 1.1),
        sky_tint=(0.0, 0.1),
        line_width_scale=(0.85, 1.15),
        line_fade=(0.0, 0.15),
        line_wear=(0.0, 0.1),
        roadside_tint=(0.0, 0.2),
        opponent_tint=(0.0, 0.3),
        camera_height_m=(-0.01, 0.01),
        camera_pitch_rad=(-0.03, 0.03),
        camera_fovy_deg=(-3.0, 3.0),
        image_noise_std=(0.0, 3.0),
    ),
    "strong": VisualRandomization(
        light_azimuth_rad=(-math.pi, math.pi),
        light_elevation_rad=(-0.7, 0.2),
        light_intensity=(0.5, 1.6),
        light_tint=(0.0, 0.25),
        asphalt_brightness=(0.55, 1.5),
        asphalt_tint=(0.0, 0.15),
        asphalt_texture_contrast=(0.05, 0.4),
        asphalt_textured_probability=0.35,
        ground_brightness=(0.5, 1.6),
        ground_tint=(0.0, 0.35),
        sky_brightness=(0.6, 1.2),
        sky_tint=(0.0, 0.3),
        line_width_scale=(0.6, 1.5),
        line_fade=(0.0, 0.35),
        line_wear=(0.0, 0.25),
        line_dashed_probability=0.3,
        roadside_hidden_probability=0.3,
        roadside_tint=(0.0, 0.6),
        opponent_tint=(0.0, 0.8),
        camera_height_m=(-0.02, 0.03),
        camera_pitch_rad=(-0.08, 0.08),
        camera_fovy_deg=(-10.0, 10.0),
        image_noise_std=(0.0, 8.0),
        image_blur_sigma_px=(0.0, 0.8),
    ),
}

PHYSICS_PRESETS: dict[str, PhysicsRandomization] = {
    "none": PhysicsRandomization(),
    "mild": PhysicsRandomization(
        mass_scale=(0.9, 1.1), friction_scale=(0.9, 1.1), motor_scale=(0.9, 1.1)
    ),
    "strong": PhysicsRandomization(
        mass_scale=(0.75, 1.3), friction_scale=(0.7, 1.2), motor_scale=(0.75, 1.2)
    ),
}

#: Shift severities (Ovadia et al. 2019): 0 is the training look, ``k`` the ``strong``
#: preset's ranges stretched from the built scene by ``k / SEVERITY_OF_STRONG`` (clipped to
#: what each field allows), so that light, textures, line wear, camera pose, noise and blur
#: all change more at each level; 3 is ``strong`` itself.
SEVERITIES = (0, 1, 2, 3, 4, 5)
SEVERITY_OF_STRONG = 3
SEVERITY_PREFIX = "severity-"


def severity_randomization(level: int) -> VisualRandomization:
    """The looks of shift severity ``level`` (see :data:`SEVERITIES`)."""
    if level not in SEVERITIES:
        raise RandomizationError(f"severity must be one of {SEVERITIES}, got {level!r}")
    factor = level / SEVERITY_OF_STRONG
    identity, strong = VisualRandomization(), VISUAL_PRESETS["strong"]
    stretched = {}
    for field in fields(VisualRandomization):
        built, wide = getattr(identity, field.name), getattr(strong, field.name)
        if field.name.endswith("_probability"):  # of a change: none in the built scene
            stretched[field.name] = built if level == 0 else min(1.0, factor * wide)
            continue
        low, high = _field_limits(field.name)
        stretched[field.name] = tuple(
            min(max(b + factor * (w - b), low), high) for b, w in zip(built, wide, strict=True)
        )
    return VisualRandomization(**stretched)


_Spec = TypeVar("_Spec", VisualRandomization, PhysicsRandomization)


def _resolve(value: str | _Spec | None, presets: dict[str, _Spec], kind: type[_Spec]) -> _Spec:
    if value is None:
        return presets["none"]
    if isinstance(value, kind):
        return value
    if isinstance(value, str):
        if value not in presets:
            raise RandomizationError(
                f"unknown {kind.__name__} preset {value!r}; choose one of {', '.join(presets)}"
            )
        return presets[value]
    raise RandomizationError(
        f"expected a preset name or a {kind.__name__}, got {type(value).__name__}"
    )


def visual_randomization(value: str | VisualRandomization | None) -> VisualRandomization:
    """The ranges of a preset name (or ``severity-K``), an instance, or None (none)."""
    if isinstance(value, str) and value.startswith(SEVERITY_PREFIX):
        level = value.removeprefix(SEVERITY_PREFIX)
        if not level.isdigit():
            raise RandomizationError(f"{value!r} names no severity: use severity-0 .. -5")
        return severity_randomization(int(level))
    return _resolve(value, VISUAL_PRESETS, VisualRandomization)


def physics_randomization(value: str | PhysicsRandomization | None) -> PhysicsRandomization:
    """The ranges of a preset name, an instance, or None (no randomisation)."""
    return _resolve(value, PHYSICS_PRESETS, PhysicsRandomization)

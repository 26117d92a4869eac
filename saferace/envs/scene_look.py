"""Per-episode looks of a randomizable scene, applied to the compiled model in place.

:class:`SceneLook` draws a look from :class:`~saferace.envs.randomization.VisualRandomization`
ranges and writes it into the ``MjModel`` (light, colours, the asphalt's and the sky's
texels, the boundary lines' pieces, roadside objects, the onboard cameras), starting each
time from the values as built. No scene is rebuilt, and a new look costs about a millisecond:

- The asphalt's noise texture and the sky come from banks of :data:`TEXTURE_BANK_SIZE`
  textures painted once per environment from the ranges (with :data:`BANK_SEED`, so every
  environment with the same ranges has the same banks) and uploaded with the model; a look
  picks an entry: the asphalt's material switches texture, and each renderer's context
  points the skybox at the entry's GL texture (:meth:`SceneLook.upload`; uploading the sky
  cost 2 ms a look). A look's sky brightness, sky tint and texture contrast are therefore
  one of the bank's 16 draws from their ranges, not a fresh one (and so are the lines'
  width and wear, below).
- Image noise is drawn once per environment as :data:`UNIT_NOISE_IMAGES` standard-normal
  images; a look scales :data:`NOISE_BANK_SIZE` consecutive ones of them, from a drawn
  start, by its noise level (drawing them anew cost 1.2 ms a look).
- The boundary lines likewise: a bank of reshaped copies of their meshes, and a look
  switches the line geoms to an entry's (uploading the reshaped lines cost 0.24 ms).

Image noise and blur are applied to each rendered onboard image
(:meth:`SceneLook.postprocess`).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import mujoco
import numpy as np

from saferace.envs.randomization import VisualRandomization
from saferace.envs.scene import (
    ASPHALT_TEXTURE,
    LINE_MESHES,
    ROADSIDE_RGBA,
    SHELL_GEOMS,
    SKY_TEXTURE,
    TEXTURE_BANK_SIZE,
    bank_texture,
)

ONBOARD_CAMERAS = ("front_camera", "stereo_left", "stereo_right")
LINES = ("left_line", "right_line")
DASHES = ("left_dashes", "right_dashes")
#: Noise images per episode; successive images get them in turn.
NOISE_BANK_SIZE = 8
#: Standard-normal noise images drawn once per environment, which episodes scale.
UNIT_NOISE_IMAGES = 64
#: Seeds the texture banks and the unit noise: the same for every environment.
BANK_SEED = 20261125
BLUR_KERNEL_SIGMAS = 1.25
_RGB = int(mujoco.mjtTextureRole.mjTEXROLE_RGB)


class SceneLook:
    """Draws looks from ``ranges`` and applies them to ``model`` (built ``randomizable``)
    and to onboard images of ``image_size`` (H, W)."""

    def __init__(
        self, model: mujoco.MjModel, ranges: VisualRandomization, image_size: tuple[int, int]
    ) -> None:
        self.model, self.ranges, self.image_size = model, ranges, image_size
        self._sun = model.light("sun").id
        self._sun_dir = model.light_dir[self._sun].copy()
        self._sun_diffuse = model.light_diffuse[self._sun].copy()
        self._head_ambient = model.vis.headlight.ambient.copy()
        self._head_diffuse = model.vis.headlight.diffuse.copy()
        self._asphalt = model.material("asphalt_material").id
        self._asphalt_rgba = model.mat_rgba[self._asphalt].copy()
        self._ground = model.geom("ground").id
        self._ground_rgba = model.geom_rgba[self._ground].copy()
        self._sky = model.texture(SKY_TEXTURE).id
        bank = np.random.default_rng(BANK_SEED)
        self._asphalt_bank, self._asphalt_contrast = self._paint_asphalt_bank(bank)
        self._sky_bank, self._sky_values = self._paint_sky_bank(bank)
        self._sky_entry = 0
        self._unit_noise: np.ndarray | None = None  # drawn at the first noisy look
        self._line_materials = [model.material(f"{name}_material").id for name in LINES]
        self._solid = [model.geom(name).id for name in LINES]
        self._dashed = [model.geom(name).id for name in DASHES]
        built_meshes = [model.mesh(f"{name}_mesh").id for name in LINE_MESHES]
        self._built_pairs = [self._pairs(mesh).copy() for mesh in built_meshes]
        # which edge of each mesh's vertex pairs is the inner one (see scene._add_ribbon and
        # scene._add_dashes): the right solid line's pairs run inner edge first
        self._inner_edge = [0 if name == "right_line" else 1 for name in LINE_MESHES]
        self._line_bank, self._line_values = self._paint_line_bank(bank)
        self._roadside = [
            model.geom(f"roadside_{kind}").id
            for kind in range(len(ROADSIDE_RGBA))
            if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"roadside_{kind}") >= 0
        ]
        self._roadside_rgba = model.geom_rgba[self._roadside].copy()
        self._opponent_shells = [
            geom
            for geom in range(model.ngeom)
            if model.geom(geom).name.startswith("car")
            and model.geom(geom).name.split("/")[-1] in SHELL_GEOMS
        ]
        self._opponent_rgba = model.geom_rgba[self._opponent_shells].copy()
        self._cameras = [  # every car's: an opponent's view (PettingZoo) has the look too
            camera
            for camera in range(model.ncam)
            if model.camera(camera).name.split("/")[-1] in ONBOARD_CAMERAS
        ]
        self._camera_pos = model.cam_pos[self._cameras].copy()
        self._camera_quat = model.cam_quat[self._cameras].copy()
        self._camera_fovy = model.cam_fovy[self._cameras].copy()
        self.image_blur_sigma_px = 0.0
        self._noise_bank: np.ndarray | None = None
        self.noise_index = 0  # images noised this episode

    def apply(self, rng: np.random.Generator) -> dict[str, Any]:
        """Draw a look with ``rng`` and write it into the model; the values drawn."""
        r = self.ranges
        drawn: dict[str, Any] = {}

        def uniform(name: str) -> float:
            drawn[name] = self._draw(name, rng)
            return drawn[name]

        def tint(name: str) -> np.ndarray:
            spread = uniform(name)
            return 1.0 + rng.uniform(-spread, spread, 3)

        azimuth, elevation = uniform("light_azimuth_rad"), uniform("light_elevation_rad")
        self._light(azimuth, elevation, uniform("light_intensity") * tint("light_tint"))
        asphalt = self._asphalt_rgba[:3] * uniform("asphalt_brightness") * tint("asphalt_tint")
        asphalt = np.clip(asphalt, 0.0, 1.0)
        self.model.mat_rgba[self._asphalt, :3] = asphalt
        drawn["asphalt_textured"] = bool(rng.random() < r.asphalt_textured_probability)
        entry = int(rng.integers(TEXTURE_BANK_SIZE))
        contrast = self._asphalt_contrast[entry] if drawn["asphalt_textured"] else 0.0
        drawn["asphalt_texture_contrast"] = contrast
        # plain asphalt untextured: sampling a texture costs a software rasteriser 8%
        self.model.mat_texid[self._asphalt, _RGB] = self._asphalt_bank[entry] if contrast else -1
        ground = self._ground_rgba[:3] * uniform("ground_brightness") * tint("ground_tint")
        self.model.geom_rgba[self._ground, :3] = np.clip(ground, 0.0, 1.0)
        self._sky_entry = int(rng.integers(TEXTURE_BANK_SIZE))
        drawn.update(self._sky_values[self._sky_entry])
        fade = uniform("line_fade")
        paint = (1.0 - fade) + fade * asphalt
        for material in self._line_materials:
            self.model.mat_rgba[material, :3] = paint
        drawn["line_dashed"] = dashed = bool(rng.random() < r.line_dashed_probability)
        for solid, dashes in zip(self._solid, self._dashed, strict=True):
            self.model.geom_rgba[solid, 3] = 0.0 if dashed else 1.0
            self.model.geom_rgba[dashes] = [*paint, 1.0 if dashed else 0.0]
        line_entry = int(rng.integers(TEXTURE_BANK_SIZE))
        self.model.geom_dataid[[*self._solid, *self._dashed]] = self._line_bank[line_entry]
        drawn.update(self._line_values[line_entry])
        self._roadside_objects(uniform("roadside_tint"), rng, drawn)
        height, pitch = uniform("camera_height_m"), uniform("camera_pitch_rad")
        self._camera(height, pitch, uniform("camera_fovy_deg"))
        noise_std = uniform("image_noise_std")
        self.image_blur_sigma_px = uniform("image_blur_sigma_px")
        self._noise_bank, self.noise_index = None, 0
        if noise_std > 0.0:
            self._noise_bank = self._scaled_noise(noise_std, int(rng.integers(UNIT_NOISE_IMAGES)))
        if self._opponent_shells:  # drawn last: a scene without opponents looks as before
            self._paint_opponents(uniform("opponent_tint"), rng)
        return drawn

    def upload(self, renderer: mujoco.Renderer) -> None:
        """Point ``renderer``'s skybox at the look's sky (all else a look changes is model
        data that every render reads).

        ``mujoco.Renderer`` uploads the model (the banks with it) once, when it is made,
        and has no public call to upload again; this uses its context as MuJoCo's own
        viewer does. The context's table of GL texture names says which texture the
        skybox draws: the sky's slot gets the picked entry's name.
        """
        renderer._gl_context.make_current()
        context = renderer._mjr_context
        context.texture[self._sky] = context.texture[self._sky_bank[self._sky_entry]]

    def postprocess(self, image: np.ndarray) -> np.ndarray:
        """``image`` blurred and noised as drawn for this episode (unchanged if neither)."""
        sigma = self.image_blur_sigma_px
        if sigma > 0.0:
            # a kernel to 1.25 sigma (3x3 up to 0.8 px): OpenCV's default 6-sigma one costs
            # 4x as much, 4% of a 64x64 step, for tails of a few percent
            size = 2 * math.ceil(BLUR_KERNEL_SIGMAS * sigma) + 1
            image = cv2.GaussianBlur(image, (size, size), sigma)
        if self._noise_bank is not None:
            self.noise_index += 1
            raise_by, lower_by = self._noise_bank[self.noise_index % NOISE_BANK_SIZE]
            image = cv2.subtract(cv2.add(image, raise_by), lower_by)  # saturating
        return image

    # ------------------------------------------------------------------ parts
    def _draw(self, name: str, rng: np.random.Generator) -> float:
        """A value of the range ``name`` (its low end when the range is a single value)."""
        low, high = getattr(self.ranges, name)
        return float(rng.uniform(low, high)) if high > low else float(low)

    def _texels(self, texture: int) -> np.ndarray:
        """The texture's texels as a writable ``(height, width, channels)`` view."""
        model = self.model
        height, width, channels = (
            model.tex_height[texture],
            model.tex_width[texture],
            model.tex_nchannel[texture],
        )
        start = model.tex_adr[texture]
        flat = model.tex_data[start : start + height * width * channels]
        return flat.reshape(height, width, channels)

    def _pairs(self, mesh: int) -> np.ndarray:
        """A line mesh's vertices as a writable ``(n, 2, 3)`` view of pairs across it."""
        start, count = self.model.mesh_vertadr[mesh], self.model.mesh_vertnum[mesh]
        return self.model.mesh_vert[start : start + count].reshape(-1, 2, 3)

    def _light(self, azimuth_rad: float, elevation_rad: float, colour: np.ndarray) -> None:
        x, y, z = self._sun_dir
        azimuth = math.atan2(y, x) + azimuth_rad
        elevation = min(max(math.atan2(-z, math.hypot(x, y)) + elevation_rad, 0.2), 1.5)
        self.model.light_dir[self._sun] = [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            -math.sin(elevation),
        ]
        self.model.light_diffuse[self._sun] = np.clip(self._sun_diffuse * colour, 0.0, 1.0)
        self.model.vis.headlight.ambient = np.clip(self._head_ambient * colour, 0.0, 1.0)
        self.model.vis.headlight.diffuse = np.clip(self._head_diffuse * colour, 0.0, 1.0)

    def _paint_asphalt_bank(self, rng: np.random.Generator) -> tuple[list[int], list[float]]:
        """Paint the asphalt bank: each entry white less a contrast drawn from the range times
        smooth noise scaled to [0, 1]; the entries' texture ids and contrasts."""
        entries, contrasts = [], []
        for entry in range(TEXTURE_BANK_SIZE):
            texture = self.model.texture(bank_texture(ASPHALT_TEXTURE, entry)).id
            contrast = self._draw("asphalt_texture_contrast", rng)
            texels = self._texels(texture)
            noise = cv2.GaussianBlur(rng.random(texels.shape[:2]), (0, 0), 1.0)
            noise = (noise - noise.min()) / max(float(np.ptp(noise)), 1e-9)
            texels[:] = np.rint(255.0 * (1.0 - contrast * noise))[..., None].astype(np.uint8)
            entries.append(texture)
            contrasts.append(contrast)
        return entries, contrasts

    def _paint_sky_bank(self, rng: np.random.Generator) -> tuple[list[int], list[dict]]:
        """Paint the sky bank: the built sky times a brightness and a per-channel tint drawn
        from the ranges; the entries' texture ids and the values each was painted with."""
        built = self._texels(self._sky).astype(float)
        entries, values = [], []
        for entry in range(TEXTURE_BANK_SIZE):
            texture = self.model.texture(bank_texture(SKY_TEXTURE, entry)).id
            drawn: dict[str, float] = {"sky_bank_entry": entry}
            for name in ("sky_brightness", "sky_tint"):
                drawn[name] = self._draw(name, rng)
            tint = 1.0 + rng.uniform(-drawn["sky_tint"], drawn["sky_tint"], 3)
            sky = built * drawn["sky_brightness"] * tint
            self._texels(texture)[:] = np.clip(sky, 0, 255).astype(np.uint8)
            entries.append(texture)
            values.append(drawn)
        return entries, values

    def _paint_line_bank(self, rng: np.random.Generator) -> tuple[np.ndarray, list[dict]]:
        """Shape the line bank: in each entry every line ``width_scale`` times as wide as
        built, and at worn vertex pairs (a share ``wear``) a random 0-50% of that: notches in
        solid lines, chipped dashes; the entries' mesh ids (a row of the four lines' per
        entry) and the values each was shaped with."""
        entries, values = [], []
        for entry in range(TEXTURE_BANK_SIZE):
            drawn = {}
            for name in ("line_width_scale", "line_wear"):
                drawn[name] = self._draw(name, rng)
            meshes = [
                self.model.mesh(bank_texture(f"{name}_mesh", entry)).id for name in LINE_MESHES
            ]
            for mesh, built, inner in zip(meshes, self._built_pairs, self._inner_edge, strict=True):
                outer = 1 - inner
                worn = rng.random(len(built)) < drawn["line_wear"]
                scale = drawn["line_width_scale"] * np.where(
                    worn, rng.uniform(0.0, 0.5, len(built)), 1.0
                )
                offset = built[:, inner] - built[:, outer]
                self._pairs(mesh)[:, inner] = built[:, outer] + scale[:, None] * offset
            entries.append(meshes)
            values.append(drawn)
        return np.array(entries), values

    def _roadside_objects(
        self, spread: float, rng: np.random.Generator, drawn: dict[str, Any]
    ) -> None:
        hidden = rng.random(len(self._roadside)) < self.ranges.roadside_hidden_probability
        drawn["roadside_hidden"] = int(hidden.sum())
        for k, geom in enumerate(self._roadside):
            colour = self._roadside_rgba[k, :3] * (1.0 + rng.uniform(-spread, spread, 3))
            self.model.geom_rgba[geom] = [*np.clip(colour, 0.0, 1.0), 0.0 if hidden[k] else 1.0]

    def _paint_opponents(self, spread: float, rng: np.random.Generator) -> None:
        """Tint each opponent's body (its shell and wing alike)."""
        cars = sorted({self.model.geom(geom).name.split("/")[0] for geom in self._opponent_shells})
        tints = {car: 1.0 + rng.uniform(-spread, spread, 3) for car in cars}
        for k, geom in enumerate(self._opponent_shells):
            tint = tints[self.model.geom(geom).name.split("/")[0]]
            colour = np.clip(self._opponent_rgba[k, :3] * tint, 0.0, 1.0)
            self.model.geom_rgba[geom, :3] = colour

    def _camera(self, height_m: float, pitch_rad: float, fovy_deg: float) -> None:
        """Raise, pitch down (about each camera's own x axis) and widen the onboard cameras."""
        tilt = np.empty(4)
        mujoco.mju_axisAngle2Quat(tilt, np.array([1.0, 0.0, 0.0]), -pitch_rad)
        for k, camera in enumerate(self._cameras):
            self.model.cam_pos[camera] = self._camera_pos[k] + [0.0, 0.0, height_m]
            quat = np.empty(4)
            mujoco.mju_mulQuat(quat, self._camera_quat[k], tilt)
            self.model.cam_quat[camera] = quat
            self.model.cam_fovy[camera] = self._camera_fovy[k] + fovy_deg

    def _scaled_noise(self, std: float, start: int) -> np.ndarray:
        """:data:`NOISE_BANK_SIZE` of the environment's unit noise images from ``start`` on
        (wrapping), times ``std``, each as its positive and negative parts (uint8: two
        saturating adds cost half of one int16)."""
        if self._unit_noise is None:
            generator = np.random.default_rng(BANK_SEED + 1)
            shape = (UNIT_NOISE_IMAGES, *self.image_size, 3)
            self._unit_noise = generator.standard_normal(shape, dtype=np.float32)
        picked = np.arange(start, start + NOISE_BANK_SIZE) % UNIT_NOISE_IMAGES
        noise = np.rint(self._unit_noise[picked] * np.float32(std))
        parts = np.stack([np.clip(noise, 0, 255), np.clip(-noise, 0, 255)], axis=1)
        return parts.astype(np.uint8)

"""MuJoCo scene of a track with the rc10 car, built with ``mujoco.MjSpec``.

The scene has what the cameras need and nothing that costs render time on a CPU:
one asphalt ribbon mesh, two white boundary-line meshes (what the networks look at,
so they are emissive and crisp even at 64x64), a start/finish line, a grass ground
plane with a coarse grid, and some roadside cones and boxes for visual structure.
Shadows and multisampling are off. Only the car's tyres and chassis collide, with the
ground plane; every other scene element is visual. A scene with opponents attaches the
car's spec once more per opponent, prefixed ``car1/``, ``car2/``..., in its own colour;
the cars' bumpers collide with each other's, never with the scenery. A ``randomizable``
scene gives the asphalt a plain white texture and adds hidden dashed lines, which domain
randomisation repaints, moves and shows in place (:mod:`saferace.envs.scene_look`); its
lines are not emissive, so that they dim with the randomised light. The texture costs a
software rasteriser about 8% of a 64x64 step; every mesh vertex drawn costs too, so the
dashed lines are drawn only when shown.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import mujoco
import numpy as np

from saferace.track import Track

CAR_XML = Path(str(resources.files("saferace.assets.vehicles.rc10").joinpath("rc10.xml")))

ASPHALT_RGBA = (0.32, 0.32, 0.34, 1.0)
LINE_RGBA = (1.0, 1.0, 1.0, 1.0)
GRASS_RGBA = (0.30, 0.50, 0.22, 1.0)
START_RGBA = (0.85, 0.10, 0.10, 1.0)
#: The opponents' body colours, in turn (the ego car is red).
OPPONENT_RGBA = (
    (0.10, 0.35, 0.85, 1.0),
    (0.95, 0.75, 0.10, 1.0),
    (0.10, 0.65, 0.30, 1.0),
    (0.60, 0.20, 0.75, 1.0),
)
#: The geom group of the ego car's own visual geoms (hidden from its onboard cameras) and of
#: every other car's (shown).
OWN_CAR_GROUP = 2
OTHER_CAR_GROUP = 1
HIDDEN_GROUP = 3  # collision geoms, and what is not worth drawing
SHELL_GEOMS = ("shell", "wing")
ROADSIDE_RGBA = ((1.0, 0.45, 0.0, 1.0), (0.15, 0.35, 0.85, 1.0), (0.95, 0.85, 0.10, 1.0))

_SURFACE_Z_M = {"asphalt": 0.002, "lines": 0.004, "start": 0.005}
ASPHALT_TEXTURE = "asphalt_texture"
ASPHALT_TEXTURE_TEXELS = 64
ASPHALT_TEXTURE_TILE_M = 1.0  # the asphalt's texture repeats every metre in x and y
SKY_TEXTURE = "sky"
SKY_TEXELS = 64
#: A randomizable scene's banks of asphalt and sky textures and of boundary-line meshes
#: (``NAME_bank_K``), painted once per environment and uploaded with the model, so that a
#: new look only picks entries (``saferace.envs.scene_look``): an upload of the sky alone
#: cost 2 ms, of the lines 0.24 ms.
TEXTURE_BANK_SIZE = 16
#: The boundary lines' solid and dashed meshes (``NAME_mesh``) of a randomizable scene.
LINE_MESHES = ("left_line", "right_line", "left_dashes", "right_dashes")
#: Dashes and gaps of a dashed line (randomizable scene); no piece of line spans two.
DASH_M = 0.5


@dataclass(frozen=True)
class SceneOptions:
    """What the scene contains and how finely it is meshed."""

    line_width_m: float = 0.07
    mesh_chord_error_m: float = 0.005
    mesh_max_step_m: float = 1.0
    roadside_spacing_m: float = 2.5
    roadside_objects: bool = True
    max_image_width: int = 640
    max_image_height: int = 480
    randomizable: bool = False


def car_prefix(index: int) -> str:
    """The name prefix of car ``index`` (0 is the ego car, whose names have none)."""
    return "" if index == 0 else f"car{index}/"


def build_scene(
    track: Track, options: SceneOptions | None = None, opponents: int = 0
) -> mujoco.MjSpec:
    """The MjSpec of ``track`` with the rc10 car and ``opponents`` more at the origin."""
    options = options or SceneOptions()
    spec = mujoco.MjSpec.from_file(str(CAR_XML))
    for index in range(1, opponents + 1):
        _attach_opponent(spec, index)
    spec.modelname = f"saferace_{track.name}"
    _configure_visual(spec, track, options)
    _add_ground_and_light(spec, track)
    s = mesh_samples(track, options.mesh_chord_error_m, options.mesh_max_step_m)
    left, right = track.boundaries_at(s)
    z_lines = _SURFACE_Z_M["lines"]
    if options.randomizable:
        _add_white_texture(spec, ASPHALT_TEXTURE, ASPHALT_TEXTURE_TEXELS)
        _add_texture_banks(spec)
        closed_left, closed_right = np.vstack([left, left[:1]]), np.vstack([right, right[:1]])
        uv = (closed_left / ASPHALT_TEXTURE_TILE_M, closed_right / ASPHALT_TEXTURE_TILE_M)
        _add_ribbon(spec, "asphalt", left, right, ASPHALT_RGBA, _SURFACE_Z_M["asphalt"], 0.0, uv)
        line_emission = 0.0  # lines dim with the randomised light
    else:
        _add_ribbon(spec, "asphalt", left, right, ASPHALT_RGBA, _SURFACE_Z_M["asphalt"], 0.0)
        line_emission = 0.6
    normals = track.centerline.normal(s)
    width = options.line_width_m
    _add_ribbon(spec, "left_line", left, left - width * normals, LINE_RGBA, z_lines, line_emission)
    _add_ribbon(
        spec, "right_line", right + width * normals, right, LINE_RGBA, z_lines, line_emission
    )
    if options.randomizable:
        _add_dashes(spec, track, dash_pieces(track, s), width, z_lines)
        _add_line_banks(spec)
    _add_start_line(spec, track)
    if options.roadside_objects:
        _add_roadside_objects(spec, track, options.roadside_spacing_m)
    return spec


def build_model(
    track: Track, options: SceneOptions | None = None, opponents: int = 0
) -> mujoco.MjModel:
    """The compiled scene of ``track`` with ``opponents`` cars besides the ego car."""
    return build_scene(track, options, opponents).compile()


def _attach_opponent(spec: mujoco.MjSpec, index: int) -> None:
    """Attach another rc10 as ``car{index}/``: its visual geoms shown to the onboard cameras
    (its steering knuckles hidden, its tyres drawn as boxes, 40 us less a 64x64 image), its
    body in the next opponent colour."""
    car = mujoco.MjSpec.from_file(str(CAR_XML))
    for geom in car.geoms:
        if geom.name.endswith("_knuckle_geom"):  # 2 cm, behind the wheels: not worth drawing
            geom.group = HIDDEN_GROUP
        elif geom.group == OWN_CAR_GROUP:
            geom.group = OTHER_CAR_GROUP
        if geom.name.endswith("_tyre_visual"):  # a cylinder costs a CPU rasteriser 4 boxes
            radius, half_width = geom.size[0], geom.size[1]
            geom.type = mujoco.mjtGeom.mjGEOM_BOX
            geom.size = [radius, radius, half_width]
        if geom.name in SHELL_GEOMS:
            geom.rgba = OPPONENT_RGBA[(index - 1) % len(OPPONENT_RGBA)]
    spec.worldbody.add_frame().attach_body(car.body("chassis"), car_prefix(index), "")


def _configure_visual(spec: mujoco.MjSpec, track: Track, options: SceneOptions) -> None:
    left, right = track.boundaries(0.5)
    span = np.ptp(np.vstack([left, right]), axis=0)
    extent = float(np.hypot(*span)) + 4.0
    spec.stat.extent = extent
    spec.visual.map.znear = 0.03 / extent  # the onboard camera sees asphalt 0.3 m ahead
    spec.visual.map.zfar = 1.5
    spec.visual.quality.shadowsize = 0
    spec.visual.quality.offsamples = 0
    spec.visual.quality.numslices = 8  # tessellation of round geoms and the skybox
    spec.visual.quality.numstacks = 4
    spec.visual.quality.numquads = 1
    spec.visual.global_.offwidth = options.max_image_width
    spec.visual.global_.offheight = options.max_image_height
    spec.visual.headlight.ambient = [0.45, 0.45, 0.45]
    spec.visual.headlight.diffuse = [0.35, 0.35, 0.35]
    spec.visual.headlight.specular = [0.0, 0.0, 0.0]


def _add_white_texture(spec: mujoco.MjSpec, name: str, texels: int) -> None:
    texture = spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D)
    texture.width = texture.height = texels
    texture.nchannel = 3
    texture.data = bytes([255]) * (3 * texels * texels)


def bank_texture(name: str, entry: int) -> str:
    """The name of entry ``entry`` of texture ``name``'s bank."""
    return f"{name}_bank_{entry}"


def _add_texture_banks(spec: mujoco.MjSpec) -> None:
    """Blank entries of the asphalt's and the sky's banks (painted by the scene's look)."""
    for entry in range(TEXTURE_BANK_SIZE):
        _add_white_texture(spec, bank_texture(ASPHALT_TEXTURE, entry), ASPHALT_TEXTURE_TEXELS)
        sky = spec.add_texture(
            name=bank_texture(SKY_TEXTURE, entry), type=mujoco.mjtTexture.mjTEXTURE_SKYBOX
        )
        sky.width, sky.height, sky.nchannel = SKY_TEXELS, 6 * SKY_TEXELS, 3
        sky.data = bytes([255]) * (3 * 6 * SKY_TEXELS * SKY_TEXELS)


def _add_line_banks(spec: mujoco.MjSpec) -> None:
    """Copies of every boundary-line mesh, one per bank entry (reshaped by the scene's
    look: a look switches the line geoms to an entry's meshes instead of uploading)."""
    for name in LINE_MESHES:
        built = spec.mesh(f"{name}_mesh")
        for entry in range(TEXTURE_BANK_SIZE):
            mesh = spec.add_mesh(name=bank_texture(f"{name}_mesh", entry))
            mesh.uservert, mesh.userface = list(built.uservert), list(built.userface)
            mesh.inertia = built.inertia


def dash_pieces(track: Track, mesh_s_m: np.ndarray) -> np.ndarray:
    """Start and end arc lengths (m) of the pieces of a dashed line: the lane meshes'
    vertices ``mesh_s_m`` split at every multiple of ``DASH_M``, keeping every other stretch."""
    s = np.union1d(mesh_s_m, np.arange(0.0, track.length_m, DASH_M))
    ends = np.append(s[1:], track.length_m)
    in_dash = np.floor(0.5 * (s + ends) / DASH_M) % 2 == 0
    return np.column_stack([s[in_dash], ends[in_dash]])


def _add_dashes(
    spec: mujoco.MjSpec, track: Track, pieces: np.ndarray, width_m: float, z_m: float
) -> None:
    """Dashed boundary lines, hidden (alpha 0) until a look shows them: separate quads
    of four vertices each (outer edge, inner edge at the piece's start, then at its end)."""
    starts, ends = pieces[:, 0], pieces[:, 1]
    first = 4 * np.arange(len(pieces))[:, None]
    for name, side in (("left_dashes", 1.0), ("right_dashes", -1.0)):
        vertices = np.empty((len(pieces), 4, 3))
        for column, s in ((0, starts), (2, ends)):
            left, right = track.boundaries_at(s)
            outer = left if side > 0 else right
            vertices[:, column, :2] = outer
            vertices[:, column + 1, :2] = outer - side * width_m * track.centerline.normal(s)
        vertices[..., 2] = z_m
        # faces up (counter-clockwise seen from above) on either side of the lane
        order = [[0, 1, 2], [1, 3, 2]] if side > 0 else [[0, 2, 1], [1, 2, 3]]
        faces = np.concatenate([first + np.array(triangle) for triangle in order])
        mesh = spec.add_mesh(name=f"{name}_mesh")
        mesh.uservert = vertices.ravel().tolist()
        mesh.userface = faces.ravel().astype(int).tolist()
        mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
        spec.worldbody.add_geom(
            name=name,
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=mesh.name,
            material="left_line_material",
            rgba=[1.0, 1.0, 1.0, 0.0],
            contype=0,
            conaffinity=0,
        )


def _add_ground_and_light(spec: mujoco.MjSpec, track: Track) -> None:
    left, right = track.boundaries(0.5)
    points = np.vstack([left, right])
    center = 0.5 * (points.min(axis=0) + points.max(axis=0))
    half = 0.5 * np.ptp(points, axis=0) + 6.0
    sky = spec.add_texture(name=SKY_TEXTURE, type=mujoco.mjtTexture.mjTEXTURE_SKYBOX)
    sky.builtin = mujoco.mjtBuiltin.mjBUILTIN_GRADIENT
    sky.rgb1 = [0.55, 0.75, 0.95]
    sky.rgb2 = [0.95, 0.97, 1.0]
    sky.width = sky.height = SKY_TEXELS
    spec.worldbody.add_geom(
        name="ground",
        type=mujoco.mjtGeom.mjGEOM_PLANE,
        pos=[center[0], center[1], 0.0],
        size=[half[0], half[1], 10.0],
        rgba=GRASS_RGBA,
        contype=1,
        conaffinity=1,
        condim=3,
    )
    spec.worldbody.add_light(
        name="sun",
        type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
        pos=[center[0], center[1], 10.0],
        dir=[0.3, 0.2, -1.0],
        diffuse=[0.55, 0.55, 0.55],
        specular=[0.1, 0.1, 0.1],
        castshadow=False,
    )


def mesh_samples(track: Track, chord_error_m: float, max_step_m: float) -> np.ndarray:
    """Arc lengths where the lane meshes have vertices: dense in turns, sparse on straights.

    The spacing keeps the chord error of the tighter boundary (radius ``1/|kappa| - w``)
    under ``chord_error_m``: ``step = sqrt(8 * chord_error * radius)``. Fewer vertices
    render faster in a software rasteriser.
    """
    knots = track.centerline.knot_s_m[:-1]
    kappa = np.abs(track.centerline.curvature(knots))
    w_right, w_left = track.widths(knots)
    inner = np.where(track.centerline.curvature(knots) > 0, w_left, w_right)
    with np.errstate(divide="ignore", over="ignore"):
        radius = np.maximum(1.0 / kappa - inner, 0.05)
    allowed = np.clip(np.sqrt(8.0 * chord_error_m * radius), 0.02, max_step_m)
    spacing = track.centerline.knot_spacing_m
    samples = [0]
    while True:
        here = samples[-1]
        reach = here + np.arange(int(allowed[here] / spacing) + 1)
        step = float(np.take(allowed, reach, mode="wrap").min())  # the tightest spot it spans
        following = here + max(1, int(step / spacing))
        if following >= len(knots):
            return knots[samples]
        samples.append(following)


def _add_ribbon(
    spec: mujoco.MjSpec,
    name: str,
    left: np.ndarray,
    right: np.ndarray,
    rgba: tuple[float, ...],
    z_m: float,
    emission: float = 0.6,
    texcoords: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """A closed flat strip between two polylines, faces up, as one visual mesh geom.

    With ``texcoords`` (``(u, v)`` of the left and the right polyline, one more row each
    than the polylines: the closing pair) the strip gets the texture ``{name}_texture``,
    and a repeated first pair closes it so that the texture does not run backwards over
    the last quad.
    """
    count = len(left)
    if texcoords is not None:
        left, right = np.vstack([left, left[:1]]), np.vstack([right, right[:1]])
    vertex_pairs = len(left)
    vertices = np.empty((2 * vertex_pairs, 3))
    vertices[0::2, :2], vertices[1::2, :2] = left, right
    vertices[:, 2] = z_m
    i = np.arange(count)
    left_i, right_i = 2 * i, 2 * i + 1
    following = (i + 1) % vertex_pairs
    left_j, right_j = 2 * following, 2 * following + 1
    faces = np.concatenate(
        [np.stack([right_i, right_j, left_i], 1), np.stack([left_i, right_j, left_j], 1)]
    )
    mesh = spec.add_mesh(name=f"{name}_mesh")
    mesh.uservert = vertices.ravel().tolist()
    mesh.userface = faces.ravel().astype(int).tolist()
    mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL
    material = spec.add_material(name=f"{name}_material", rgba=list(rgba))
    material.emission = emission
    material.specular = 0.0
    if texcoords is not None:
        uv = np.empty((2 * vertex_pairs, 2))
        uv[0::2], uv[1::2] = texcoords
        mesh.usertexcoord = uv.ravel().tolist()
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = f"{name}_texture"
    spec.worldbody.add_geom(
        name=name,
        type=mujoco.mjtGeom.mjGEOM_MESH,
        meshname=mesh.name,
        material=material.name,
        contype=0,
        conaffinity=0,
        group=0,
    )


def _add_start_line(spec: mujoco.MjSpec, track: Track) -> None:
    w_right, w_left = (float(w) for w in track.widths(0.0))
    center = track.centerline.position(0.0) + 0.5 * (w_left - w_right) * track.centerline.normal(
        0.0
    )
    yaw = float(track.centerline.heading(0.0))
    spec.worldbody.add_geom(
        name="start_line",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        pos=[center[0], center[1], _SURFACE_Z_M["start"]],
        quat=[np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)],
        size=[0.04, 0.5 * (w_left + w_right), 0.001],
        rgba=START_RGBA,
        contype=0,
        conaffinity=0,
    )


def _add_roadside_objects(spec: mujoco.MjSpec, track: Track, spacing_m: float) -> None:
    """Cones, boxes and posts beside the lane, never on any part of it (fixed layout per track).

    Each kind is merged into one mesh: a draw call costs more than its triangles in a
    software renderer.
    """
    rng = np.random.default_rng(0)
    projector = track.projector()
    placed: list[list[np.ndarray]] = [[] for _ in ROADSIDE_SHAPES]
    for s in np.arange(0.5 * spacing_m, track.length_m, spacing_m):
        side = 1.0 if rng.random() < 0.5 else -1.0
        w_right, w_left = track.widths(s)
        offset = side * ((w_left if side > 0 else w_right) + rng.uniform(0.3, 1.0))
        xy = track.centerline.position(s) + offset * track.centerline.normal(s)
        projector.reset()
        s_near, e_y = projector.project(*xy)
        near_right, near_left = track.widths(s_near)
        if e_y > near_left + 0.25 or e_y < -near_right - 0.25:
            placed[sum(len(p) for p in placed) % len(ROADSIDE_SHAPES)].append(xy)
    for kind, (positions, shape, rgba) in enumerate(
        zip(placed, ROADSIDE_SHAPES, ROADSIDE_RGBA, strict=True)
    ):
        if not positions:
            continue
        vertices, faces = shape
        all_vertices = np.concatenate([vertices + np.array([*xy, 0.0]) for xy in positions])
        all_faces = np.concatenate([faces + i * len(vertices) for i in range(len(positions))])
        mesh = spec.add_mesh(name=f"roadside_{kind}_mesh")
        mesh.uservert = all_vertices.ravel().tolist()
        mesh.userface = all_faces.ravel().astype(int).tolist()
        spec.worldbody.add_geom(
            name=f"roadside_{kind}",
            type=mujoco.mjtGeom.mjGEOM_MESH,
            meshname=mesh.name,
            rgba=list(rgba),
            contype=0,
            conaffinity=0,
        )


def _prism(
    radius_m: float, height_m: float, sides: int, top_scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and outward faces of a closed prism (``top_scale`` 0 gives a pyramid)."""
    angles = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False) + np.pi / sides
    ring = np.column_stack([np.cos(angles), np.sin(angles)]) * radius_m
    bottom = np.column_stack([ring, np.zeros(sides)])
    top = np.column_stack([ring * max(top_scale, 1e-3), np.full(sides, height_m)])
    vertices = np.vstack([bottom, top])
    i = np.arange(sides)
    j = (i + 1) % sides
    walls = np.concatenate([np.stack([i, j, sides + j], 1), np.stack([i, sides + j, sides + i], 1)])
    caps = np.concatenate(
        [
            np.stack([np.zeros(sides - 2, int), i[2:], i[1:-1]], 1),
            np.stack([np.full(sides - 2, sides), sides + i[1:-1], sides + i[2:]], 1),
        ]
    )
    return vertices, np.concatenate([walls, caps])


#: Cone, box and post, in the order of ROADSIDE_RGBA.
ROADSIDE_SHAPES = (
    _prism(0.06, 0.16, 8, 0.15),
    _prism(0.14, 0.2, 4, 1.0),
    _prism(0.035, 0.45, 6, 1.0),
)

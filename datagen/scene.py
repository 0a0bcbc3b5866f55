"""Scene descriptions and their random sampling — plain numpy, no Blender.

A `SceneSpec` says everything a frame shows: camera (OpenCV K and a trajectory over the
shutter), board pose and look, light, background, clutter, occluders, distractor boards,
the target illuminance and the exposure time. `sample_scene(rng, config)` draws one from an
explicit generator, so frame ``i`` of a run is a pure function of (seed, i, config);
`blender_scenes.render_scene` turns a spec into pixels and knows nothing about randomness.

World frame: Z up, metres. The board's centre sits at the origin; its printed face looks
along ``-Z_board`` (OpenCV's board frame: X right, Y down, Z into the board).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from blender_scenes.conversions import rigid
from datagen.sensor import SensorParams, luminance_of_paper

HDRI_NAMES = ("city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset")
SHAPE_KINDS = ("cube", "sphere", "cylinder", "cone", "icosphere")
SURFACE_KINDS = ("plain", "noise", "wave", "checker", "brick", "voronoi", "poster")
# Bundled scikit-image photographs (no download) used as posters and object textures.
POSTER_NAMES = ("astronaut", "brick", "camera", "chelsea", "coffee", "grass", "gravel", "rocket", "text", "page", "moon")
# Boards that are *not* the target: plain chessboards and ChArUco boards of other
# dictionaries or other marker IDs (names are parsed by blender_scenes.textures).
DISTRACTOR_NAMES = (
    "chessboard-7x5", "chessboard-9x6", "chessboard-5x5", "chessboard-4x3",
    "charuco-5x5-DICT_4X4_50", "charuco-5x5-DICT_6X6_250", "charuco-7x5-DICT_5X5_100-ids12",
    "charuco-5x5-DICT_5X5_50-ids12", "charuco-5x5-DICT_ARUCO_ORIGINAL", "aruco-grid-4x3-DICT_5X5_50",
)
BOARD_KINDS = ("matte", "glossy", "monitor")
LIGHT_KINDS = ("AREA", "SPOT", "POINT", "SUN")

WARM, NEUTRAL, COOL = (1.0, 0.78, 0.55), (1.0, 1.0, 1.0), (0.8, 0.88, 1.0)
STRONG_COLOURS = ((1.0, 0.25, 0.2), (0.25, 1.0, 0.3), (0.3, 0.4, 1.0), (0.9, 0.3, 1.0), (1.0, 0.6, 0.1))


@dataclass
class Surface:
    """A procedural or photographic material for walls, floors and objects."""

    kind: str
    color_a: tuple[float, float, float]
    color_b: tuple[float, float, float]
    scale: float
    roughness: float
    poster: str = ""


@dataclass
class Shape:
    """A primitive (unit size, centred) placed by ``matrix`` (world, with scale)."""

    kind: str
    matrix: np.ndarray
    surface: Surface
    role: str  # "room", "clutter", "occluder", "shadow-caster"


@dataclass
class Light:
    """A lamp; it shines along its local -Z. ``power``: W (sun: W/m^2), relative units."""

    kind: str
    matrix: np.ndarray
    power: float
    color: tuple[float, float, float]
    size: float = 0.1
    spot_size_deg: float = 45.0
    spot_blend: float = 0.2


@dataclass
class World:
    hdri: str
    rotation_deg: float
    strength: float


@dataclass
class BoardLook:
    """How the board is made: matte paper, glossy print or a monitor showing it."""

    kind: str
    white: float  # albedo of the paper (monitor: of its white pixels as emission)
    black: float
    roughness: float
    specular: float
    emission: float = 0.0


@dataclass
class Distractor:
    name: str
    matrix: np.ndarray  # world from the distractor's plane (its centre), rigid
    width_m: float
    look: BoardLook


@dataclass
class SceneSpec:
    """Everything one frame shows; `blender_scenes.render_scene` renders exactly this."""

    width: int
    height: int
    K: np.ndarray
    trajectory: np.ndarray  # (3, 4, 4) world from OpenCV camera at shutter start, centre, end
    exposure_s: float
    board_present: bool
    board_matrix: np.ndarray  # (4, 4) world from board frame, rigid
    board_look: BoardLook
    margin_m: float
    world: World
    lights: list[Light]
    shapes: list[Shape]
    distractors: list[Distractor]
    lux: float
    render_seed: int
    samples: int
    tags: dict = field(default_factory=dict)
    denoise: bool = False  # OpenImageDenoise on the render: for a render many frames share (evaluate.paper.sequences)
    # A slightly bent print (`bend_profile`): the sag at the middle as a fraction of the bent length
    # (> 0 bulges towards the camera's side, the printed face's -Z), bent along board X (axis 0) or Y (1).
    bend: float = 0.0
    bend_axis: int = 0

    @property
    def camera_matrix(self) -> np.ndarray:
        """World from OpenCV camera at the shutter centre (the labelled pose)."""
        return self.trajectory[1]

    @property
    def shaken(self) -> bool:
        return not np.allclose(self.trajectory[0], self.trajectory[2])


@dataclass(frozen=True)
class SceneConfig:
    """Ranges and probabilities of the scene sampler (defaults: the training distribution)."""

    width: int = 320
    height: int = 240
    hfov_deg: tuple[float, float] = (45.0, 85.0)  # webcams to wide action cameras
    principal_jitter_px: float = 6.0
    lux: tuple[float, float] = (0.2, 1000.0)  # log-uniform illuminance at the board
    board_diag_frac: tuple[float, float] = (0.25, 1.6)  # board diagonal / image width
    max_view_angle_deg: float = 65.0
    out_of_frame_p: float = 0.2  # aim away from the board centre so part of it leaves the frame
    negative_p: float = 0.1
    distractor_p: float = 0.3
    shake_p: float = 0.5
    max_angular_speed: float = 4.0  # rad/s (hand-held shake)
    max_linear_speed: float = 0.4  # m/s
    lamp_count: tuple[int, int] = (0, 3)
    spot_p: float = 0.35
    shadow_p: float = 0.4
    occluder_p: float = 0.25
    clutter_count: tuple[int, int] = (0, 5)
    clutter_kinds: tuple[str, ...] = SHAPE_KINDS
    board_kinds_p: tuple[float, float, float] = (0.6, 0.3, 0.1)
    samples: int = 4
    sensor: SensorParams = SensorParams()
    distractor_names: tuple[str, ...] = DISTRACTOR_NAMES
    # Random boards of every size (datagen.family): the board's apparent square width, as a fraction of
    # the image width, drawn log-uniformly here; `fitted_diag_frac` turns it into board_diag_frac.
    square_frac: tuple[float, float] | None = None
    bend_p: float = 0.0  # probability of a bent print
    max_bend: float = 0.02  # largest sag / bent length

    @classmethod
    def clean(cls, **overrides) -> "SceneConfig":
        """Well lit, no shake, no occluders or distractors, matte board, noiseless sensor: for label checks."""
        base = cls(lux=(300.0, 700.0), negative_p=0.0, distractor_p=0.0, shake_p=0.0, spot_p=0.0, shadow_p=0.0,
                   occluder_p=0.0, out_of_frame_p=0.0, board_diag_frac=(0.6, 1.2), max_view_angle_deg=45.0,
                   board_kinds_p=(1.0, 0.0, 0.0), samples=32, sensor=SensorParams(noise=False))
        return replace(base, **overrides)


# Random boards of a family (datagen.render --family): squares 10-64 px wide at 320 px (a 3x3 board is
# never a speck, a 25x25 board is seen in part, close), bent prints, and distractors without chessboard
# corners (ArUco grids): a ChArUco board or chessboard that is not labelled would teach a board-agnostic
# corner detector to miss real corners.
RANDOM_BOARD_SCENE = dict(square_frac=(1 / 32, 1 / 5), board_diag_frac=(0.25, 4.0), bend_p=0.3, max_bend=0.02,
                          distractor_names=("aruco-grid-4x3-DICT_5X5_50", "aruco-grid-5x4-DICT_4X4_50",
                                            "aruco-grid-3x3-DICT_6X6_250", "aruco-grid-4x4-DICT_APRILTAG_36h11"))


def random_board_config(config: SceneConfig) -> SceneConfig:
    """``config`` for frames of random boards of every size (`RANDOM_BOARD_SCENE`)."""
    return replace(config, **RANDOM_BOARD_SCENE)


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def unit_vector(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def aim_lamp(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World from lamp: at ``position``, shining (Blender lamps: along their -Z) at ``target``."""
    z = -unit_vector(target - position)
    x = unit_vector(np.cross(np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([1.0, 0.0, 0.0]), z))
    return rigid(np.column_stack([x, np.cross(z, x), z]), position)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 0.0, 1.0]), roll_deg: float = 0.0) -> np.ndarray:
    """World from OpenCV camera (Z forward, Y down) at ``eye`` looking at ``target``."""
    z = unit_vector(np.asarray(target, float) - np.asarray(eye, float))
    if abs(float(z @ up)) > 0.999:
        up = np.array([0.0, 1.0, 0.0])
    x = unit_vector(np.cross(z, -up))  # image right
    y = np.cross(z, x)  # image down
    rotation = np.column_stack([x, y, z])
    roll, _ = cv2.Rodrigues(np.array([0.0, 0.0, math.radians(roll_deg)]))
    return rigid(rotation @ roll, eye)


def _random_rotation(rng: np.random.Generator, max_angle_rad: float = math.pi) -> np.ndarray:
    axis = unit_vector(rng.normal(size=3))
    rotation, _ = cv2.Rodrigues(axis * rng.uniform(0.0, max_angle_rad))
    return rotation


def _direction_in_cone(rng: np.random.Generator, axis: np.ndarray, max_angle_deg: float) -> np.ndarray:
    """A direction within ``max_angle_deg`` of ``axis``, uniform over the cone's solid angle."""
    cos_max = math.cos(math.radians(max_angle_deg))
    cos_t = rng.uniform(cos_max, 1.0)
    phi = rng.uniform(0.0, 2 * math.pi)
    sin_t = math.sqrt(1.0 - cos_t**2)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = unit_vector(np.cross(axis, helper))
    v = np.cross(axis, u)
    return unit_vector(cos_t * axis + sin_t * (math.cos(phi) * u + math.sin(phi) * v))


def _colour(rng: np.random.Generator) -> tuple[float, float, float]:
    return tuple(float(c) for c in rng.uniform(0.05, 0.9, size=3))


def sample_surface(rng: np.random.Generator) -> Surface:
    kind = SURFACE_KINDS[rng.integers(len(SURFACE_KINDS))]
    return Surface(kind=kind, color_a=_colour(rng), color_b=_colour(rng), scale=_log_uniform(rng, 1.0, 40.0),
                   roughness=float(rng.uniform(0.2, 1.0)),
                   poster=POSTER_NAMES[rng.integers(len(POSTER_NAMES))] if kind == "poster" else "")


def sample_board_look(rng: np.random.Generator, probabilities=(0.6, 0.3, 0.1)) -> BoardLook:
    kind = BOARD_KINDS[rng.choice(3, p=np.asarray(probabilities) / np.sum(probabilities))]
    if kind == "matte":
        return BoardLook(kind, white=float(rng.uniform(0.65, 0.9)), black=float(rng.uniform(0.02, 0.08)),
                         roughness=float(rng.uniform(0.6, 1.0)), specular=float(rng.uniform(0.0, 0.3)))
    if kind == "glossy":
        return BoardLook(kind, white=float(rng.uniform(0.6, 0.9)), black=float(rng.uniform(0.01, 0.05)),
                         roughness=float(rng.uniform(0.03, 0.3)), specular=float(rng.uniform(0.4, 1.0)))
    return BoardLook(kind, white=0.02, black=0.01, roughness=float(rng.uniform(0.02, 0.15)),
                     specular=float(rng.uniform(0.3, 0.8)), emission=_log_uniform(rng, 0.3, 3.0))


def _camera_K(rng: np.random.Generator, config: SceneConfig) -> np.ndarray:
    w, h = config.width, config.height
    fx = (w / 2.0) / math.tan(math.radians(rng.uniform(*config.hfov_deg)) / 2.0)
    fy = fx  # square pixels, as webcams have (non-square ones mis-project in Blender when fy > fx: measured 0.8 px)
    cx = (w - 1) / 2.0 + rng.uniform(-1, 1) * config.principal_jitter_px
    cy = (h - 1) / 2.0 + rng.uniform(-1, 1) * config.principal_jitter_px
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def exposure_time_for(lux: float, look: BoardLook, sensor: SensorParams) -> float:
    """The exposure an auto-exposure webcam settles on when metering the board (before rendering:
    shake blur depends on it). The board's mean luminance stands for the scene's."""
    mean_albedo = 0.5 * (look.white + look.black) if look.kind != "monitor" else 0.5
    luminance = luminance_of_paper(lux, mean_albedo)
    rate = luminance * (math.pi / (4.0 * sensor.f_number**2)) * sensor.electrons_per_lux_s
    wanted = sensor.target_level * sensor.full_well
    return float(np.clip(wanted / max(rate, 1e-12), sensor.min_exposure_s, sensor.max_exposure_s))


def _shake_trajectory(rng: np.random.Generator, centre: np.ndarray, exposure_s: float, config: SceneConfig) -> np.ndarray:
    """Camera poses at the start, centre and end of the shutter for a constant-velocity shake."""
    omega = unit_vector(rng.normal(size=3)) * _log_uniform(rng, 0.05, config.max_angular_speed)
    velocity = unit_vector(rng.normal(size=3)) * _log_uniform(rng, 0.005, config.max_linear_speed)
    poses = []
    for fraction in (-0.5, 0.0, 0.5):
        dt = fraction * exposure_s
        delta, _ = cv2.Rodrigues(omega * dt)  # about the camera's own axes
        pose = centre.copy()
        pose[:3, :3] = centre[:3, :3] @ delta
        pose[:3, 3] = centre[:3, 3] + centre[:3, :3] @ (velocity * dt)
        poses.append(pose)
    return np.stack(poses)


def _light_colour(rng: np.random.Generator) -> tuple[float, float, float]:
    if rng.random() < 0.15:
        return STRONG_COLOURS[rng.integers(len(STRONG_COLOURS))]
    base = (WARM, NEUTRAL, COOL)[rng.integers(3)]
    t = rng.uniform(0.0, 1.0)
    return tuple(float((1 - t) * 1.0 + t * c) for c in base)


def _sample_lamp(rng: np.random.Generator, kind: str, board_normal: np.ndarray, board_size: float, world_strength: float) -> Light:
    """A lamp in front of the board, aimed near it, with irradiance at the board relative to the world's."""
    direction = _direction_in_cone(rng, board_normal, 75.0)
    distance = _log_uniform(rng, 0.4, 3.0)
    position = direction * distance
    aim = rng.uniform(-0.6, 0.6, size=3) * board_size
    matrix = aim_lamp(position, aim)
    irradiance = world_strength * _log_uniform(rng, 0.3, 30.0)
    if kind == "SUN":
        return Light(kind, matrix, power=irradiance, color=_light_colour(rng), size=float(rng.uniform(0.0, 0.05)))
    if kind == "AREA":
        size = _log_uniform(rng, 0.02, 0.8)
        return Light(kind, matrix, power=irradiance * math.pi * distance**2, color=_light_colour(rng), size=size)
    light = Light(kind, matrix, power=irradiance * 4 * math.pi * distance**2, color=_light_colour(rng),
                  size=_log_uniform(rng, 0.002, 0.1))
    if kind == "SPOT":
        light.spot_size_deg = float(rng.uniform(8.0, 45.0))
        light.spot_blend = float(rng.uniform(0.05, 0.6))
    return light


def _shape_between(rng: np.random.Generator, start: np.ndarray, end: np.ndarray, lo: float, hi: float,
                   size: float, role: str) -> Shape:
    """A primitive on the segment start -> end (fraction lo..hi from start), a few cm off-axis."""
    point = start + rng.uniform(lo, hi) * (end - start)
    point = point + rng.normal(scale=0.3 * size, size=3)
    kind = SHAPE_KINDS[rng.integers(len(SHAPE_KINDS))]
    scale = np.diag([*(size * rng.uniform(0.3, 1.0, size=3)), 1.0])
    if role == "occluder" and rng.random() < 0.5:
        kind = "cylinder"  # a rod or a finger across the board
        scale = np.diag([size * 0.15, size * 0.15, size * 3.0, 1.0])
    return Shape(kind, rigid(_random_rotation(rng), point) @ scale, sample_surface(rng), role)


def sample_scene(rng: np.random.Generator, board_size_m: tuple[float, float], config: SceneConfig = SceneConfig()) -> SceneSpec:
    """Draw one scene. ``board_size_m``: (width, height) of the board's square grid in metres."""
    board_w, board_h = board_size_m
    board_diag = math.hypot(board_w, board_h)
    K = _camera_K(rng, config)
    negative = bool(rng.random() < config.negative_p)

    # The board: centred at the origin, its face towards a random direction above the horizon.
    normal = _direction_in_cone(rng, np.array([0.0, 0.0, 1.0]), 85.0)
    normal = unit_vector(np.array([normal[0], normal[1], abs(normal[2]) * 0.8 + 0.05]))
    z_board = -normal
    # Horizontal X for a tilted board; for one facing (nearly) straight up, any X across the face.
    # Both are crossed with the face normal: a fixed X there was not perpendicular to it, and the
    # resulting sheared "rotation" put labels up to a sixth of a square off in 0.5 % of frames.
    helper = np.array([0.0, 0.0, 1.0]) if abs(z_board[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x_board = unit_vector(np.cross(helper, z_board))
    spin, _ = cv2.Rodrigues(z_board * rng.uniform(-math.pi, math.pi))
    x_board = spin @ x_board
    rotation = np.column_stack([x_board, np.cross(z_board, x_board), z_board])
    board_matrix = rigid(rotation, -rotation @ np.array([board_w / 2.0, board_h / 2.0, 0.0]))

    # The camera: in a cone around the board's normal, at a distance giving the sampled size.
    diag_frac = _log_uniform(rng, *config.board_diag_frac)
    distance = K[0, 0] * board_diag / (diag_frac * config.width)
    eye = _direction_in_cone(rng, normal, config.max_view_angle_deg) * distance
    spread = 0.6 if rng.random() < config.out_of_frame_p else 0.12
    target = rotation @ np.append(rng.uniform(-spread, spread, size=2) * (board_w, board_h), 0.0)
    roll = float(rng.uniform(-35.0, 35.0))
    centre = look_at(eye, target, roll_deg=roll)
    # Close and oblique, part of the board could reach behind the lens: back off until the whole
    # board is at least 3 cm in front of the camera.
    outline = np.array([[0, 0, 0], [board_w, 0, 0], [0, board_h, 0], [board_w, board_h, 0]]) @ rotation.T + board_matrix[:3, 3]
    while np.min((outline - centre[:3, 3]) @ centre[:3, 2]) < 0.03:
        eye = eye * 1.1
        centre = look_at(eye, target, roll_deg=roll)

    look = sample_board_look(rng, config.board_kinds_p)
    # White paper around the grid, as printed; a few fixed widths so the texture is drawn once per width.
    margin_m = float(rng.choice([0.03, 0.06, 0.09, 0.12])) * board_w
    lux = _log_uniform(rng, *config.lux)
    exposure_s = exposure_time_for(lux, look, config.sensor)
    shake = bool(rng.random() < config.shake_p)
    trajectory = _shake_trajectory(rng, centre, exposure_s, config) if shake else np.stack([centre] * 3)

    world = World(HDRI_NAMES[rng.integers(len(HDRI_NAMES))], float(rng.uniform(0, 360)), _log_uniform(rng, 0.05, 2.0))
    lights: list[Light] = []
    for _ in range(int(rng.integers(config.lamp_count[0], config.lamp_count[1] + 1))):
        kind = ("AREA", "POINT", "SUN")[rng.integers(3)]
        lights.append(_sample_lamp(rng, kind, normal, board_diag, world.strength))
    if rng.random() < config.spot_p:  # a pool of light on part of the board
        lights.append(_sample_lamp(rng, "SPOT", normal, board_diag, world.strength * 5.0))

    shapes: list[Shape] = []
    # Room: a wall behind the board and a floor below it.
    wall_offset = _log_uniform(rng, 0.003, 1.5)
    wall = rigid(rotation, rotation @ np.array([0.0, 0.0, wall_offset])) @ np.diag([8.0, 8.0, 1.0, 1.0])
    shapes.append(Shape("plane", wall, sample_surface(rng), "room"))
    floor_z = min(-board_diag * rng.uniform(0.5, 2.0), eye[2] - 0.05)
    shapes.append(Shape("plane", rigid(np.eye(3), [0.0, 0.0, floor_z]) @ np.diag([10.0, 10.0, 1.0, 1.0]),
                        sample_surface(rng), "room"))
    for _ in range(int(rng.integers(config.clutter_count[0], config.clutter_count[1] + 1))):
        position = rotation @ np.array([*rng.uniform(-3, 3, size=2) * board_diag, rng.uniform(-0.3, 0.05)])
        size = _log_uniform(rng, 0.03, 0.4)
        if np.linalg.norm(position - eye) < size + 0.05:
            continue  # keep clear of the lens
        kind = config.clutter_kinds[rng.integers(len(config.clutter_kinds))]
        shapes.append(Shape(kind, rigid(_random_rotation(rng), position) @ np.diag([size, size, size, 1.0]),
                            sample_surface(rng), "clutter"))
    lamps = [light for light in lights if light.kind != "SUN"]
    if lamps and rng.random() < config.shadow_p:  # something between a lamp and the board
        lamp = lamps[rng.integers(len(lamps))]
        shapes.append(_shape_between(rng, np.zeros(3), lamp.matrix[:3, 3], 0.15, 0.6, board_diag * rng.uniform(0.15, 0.5),
                                     "shadow-caster"))
    if rng.random() < config.occluder_p:  # something between the camera and the board
        aim = rotation @ np.append(rng.uniform(-0.5, 0.5, size=2) * (board_w, board_h), 0.0)
        occluder = _shape_between(rng, eye, aim, 0.3, 0.8, board_diag * rng.uniform(0.1, 0.35), "occluder")
        if np.linalg.norm(occluder.matrix[:3, 3] - eye) > 0.05:
            shapes.append(occluder)

    distractors: list[Distractor] = []
    if negative or rng.random() < config.distractor_p:
        count = 1 if negative else int(rng.integers(1, 3))
        for k in range(count):
            name = config.distractor_names[rng.integers(len(config.distractor_names))]
            if negative and k == 0:  # in the target's place, so the camera looks right at it
                place = rigid(rotation, np.zeros(3))
            else:
                offset = np.append(rng.choice([-1.0, 1.0]) * rng.uniform(1.1, 2.0) * board_w, rng.uniform(-1, 1) * board_h)
                tilt = _random_rotation(rng, math.radians(30))
                place = rigid(rotation @ tilt, rotation @ np.append(offset, -0.002))
            distractors.append(Distractor(name, place, board_w * rng.uniform(0.6, 1.5), sample_board_look(rng)))

    tags = {
        "negative": negative, "board_kind": look.kind, "hdri": world.hdri, "lamps": len(lights),
        "spot": any(l.kind == "SPOT" for l in lights), "shadow_caster": any(s.role == "shadow-caster" for s in shapes),
        "occluder": any(s.role == "occluder" for s in shapes), "distractors": len(distractors), "shake": shake,
    }
    render_seed = int(rng.integers(0, 2**31 - 1))
    bend, bend_axis = 0.0, 0
    # Drawn last, and only when enabled, so that scenes of configurations without bends stay as they were.
    if config.bend_p > 0 and rng.random() < config.bend_p:
        bend = float(rng.uniform(-1.0, 1.0) * config.max_bend)
        bend_axis = int(rng.integers(2))
        tags["bend"] = bend
    elif config.bend_p > 0:
        tags["bend"] = 0.0
    return SceneSpec(
        width=config.width, height=config.height, K=K, trajectory=trajectory, exposure_s=exposure_s,
        board_present=not negative, board_matrix=board_matrix, board_look=look, margin_m=margin_m,
        world=world, lights=lights, shapes=shapes, distractors=distractors, lux=lux,
        render_seed=render_seed, samples=config.samples, tags=tags, bend=bend, bend_axis=bend_axis,
    )


def fitted_diag_frac(squares: tuple[int, int], config: SceneConfig) -> tuple[float, float]:
    """The board_diag_frac range that gives a board of ``squares`` (x, y) squares the apparent square width
    ``config.square_frac`` (fractions of the image width), within ``config.board_diag_frac``: a 3x3 board
    is then never a speck and a 25x25 board is seen in part, close enough for its squares to be found.
    Without square_frac, board_diag_frac itself."""
    if config.square_frac is None:
        return config.board_diag_frac
    diagonal = math.hypot(*squares)  # in squares
    low = min(max(config.square_frac[0] * diagonal, config.board_diag_frac[0]), config.board_diag_frac[1])
    high = max(min(config.square_frac[1] * diagonal, config.board_diag_frac[1]), low)
    return low, high


BEND_SEGMENTS = 48  # straight pieces of a bent board's mesh; labels follow the same pieces exactly


def bend_profile(spec: SceneSpec, board_size_m: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """A bent board's shape: (knots (S+1,), z (S+1,)) metres along the bent axis of the board frame
    (spanning the printed sheet, margins included) and the sheet's Z there: a parabola sampled at the
    knots, zero at both ends, ``-spec.bend`` x the sheet's length at the middle. Between knots (and
    beyond the last, the partial texture pixel) the sheet is straight: z is ``np.interp`` of these."""
    length = board_size_m[spec.bend_axis] + 2 * spec.margin_m
    knots = np.linspace(-spec.margin_m, length - spec.margin_m, BEND_SEGMENTS + 1)
    t = (knots + spec.margin_m) / length * 2.0 - 1.0
    return knots, -spec.bend * length * (1.0 - t * t)


def bent_points(points: np.ndarray, spec: SceneSpec, board_size_m: tuple[float, float]) -> np.ndarray:
    """(N, 3) board-frame points of the flat board -> (N, 3) where they lie on the (possibly) bent sheet.

    The sheet bends without moving along X and Y (the texture keeps its board coordinates), so a
    printed point (X, Y, 0) goes to (X, Y, z(X or Y)); exact for the mesh `blender_scenes` builds."""
    points = np.array(points, dtype=np.float64, copy=True)
    if spec.bend == 0.0:
        return points
    knots, z = bend_profile(spec, board_size_m)
    points[:, 2] += np.interp(points[:, spec.bend_axis], knots, z)
    return points

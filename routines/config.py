"""The cell description (``cell.yaml``): what robot, which cameras, how mounted, which target.

THE ROBOT NEVER MOVES unless the file names real hardware: ``robot.driver: ur`` with a
``host``. Without a file, the packaged simulated cell (``mocks/default_cell.yaml``) is used.
Every key, its unit and its default, and how a bad one is refused: docs/FORMATS.md. The keys
each section accepts are declared once, in :data:`CELL_KEYS`.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from importlib import resources
from inspect import signature
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.drivers.ur import cell_options
from slidecal.drivers.ur_pose import ur_pose_from_T
from slidecal.mocks import camera as simcam
from slidecal.mocks.camera import SimCamera
from slidecal.mocks.render import Photo
from slidecal.mocks.robot import SPEED_LIMITS, KinematicError
from slidecal.routines.devices import OAK_CAMERA_KEYS, OAK_RIG_KEYS, UVC_CAMERA_KEYS
from slidecal.routines.ops.verdict import Limits, limits_from_dict
from slidecal.routines.schema import (
    CELL_SECTIONS,
    Fields,
    load_yaml,
    parse_yaml,
)
from slidecal.routines.session import (
    CAMERA_DRIVERS,
    OAK_SOCKET,
    ROBOT_DRIVERS,
    camera_spec,
    options_from_dict,
    options_to_dict,
    target_from_dict,
    target_to_dict,
    transform_from_dict,
    transform_to_dict,
    ur_pose_field,
)
from slidecal.solver.camera import distortion_model, zero_distortion
from slidecal.solver.degeneracy import nominal_K
from slidecal.solver.errors import InputError
from slidecal.solver.problem import MOUNTS, CameraSpec, ModelOptions, Target

CELL_FORMAT = "slidecal.cell/1"
CELL_MOUNTS = ("eye_in_hand", "eye_to_hand")
#: The hand-eye and target-pose keys per mount (the result file's names)
POSE_NAMES = {mount: (m.hand_eye, m.target) for mount, m in MOUNTS.items()}
CAMERA_PRESETS = ("r1", "oak_d_like")
DEFAULT_CELL = "default_cell.yaml"

#: ``simulation.kinematic_error``'s defaults: the sizes of a random simulated arm
KINEMATIC_ERROR_DEFAULTS = {
    k: p.default for k, p in signature(KinematicError.random).parameters.items() if k != "rng"
}

#: ``simulation.cameras.<name>.photo``: the fields of ``slidecal.mocks.render.Photo``
#: (photograph-like imaging) a cell file may set.
PHOTO_KEYS = tuple(f.name for f in fields(Photo))

#: The keys every section of a cell file accepts (``target``, ``options`` and ``plan`` take
#: ``TARGET_KEYS``, ``OPTIONS_KEYS`` and :data:`PLAN_KEYS`): add a key here, then read it.
CELL_KEYS: dict[str, tuple[str, ...]] = {
    "": CELL_SECTIONS,
    "robot": (
        "driver",
        "host",
        "model",
        "tcp",
        "speed_mps",
        "accel_mps2",
        "settle_s",
        "start_pose",
        "start_q",
        "workspace",
        "limits",
        "take_control",  # ur only; validated by slidecal.drivers.ur.cell_options
        "upper_range_registers",  # ur only; likewise
        "payload",
    ),
    "robot.workspace": ("min_m", "max_m"),
    "robot.limits": (*SPEED_LIMITS, "z_min_m", "move_timeout_s"),  # the simulated arm's
    # the camera drivers' own fields are declared beside the code that reads them
    "cameras": OAK_RIG_KEYS,
    "cameras.list[].oak": ("name", "width", "height", *OAK_CAMERA_KEYS),
    "cameras.list[].uvc": ("name", "width", "height", *UVC_CAMERA_KEYS),
    "approximate.eye_in_hand": ("T_base_board", "T_tool_cam", "standoff_m"),
    "approximate.eye_to_hand": ("T_base_cam", "T_tool_board", "standoff_m"),
    "simulation": (
        "seed",
        "camera_preset",
        "cameras",
        "rig",
        "noise",
        "target_jitter",
        "kinematic_error",
        "board_bow_mm",
    ),
    # a simulated camera's fields but its name (its ``dist`` is ``distortion``)
    "simulation.cameras.*": tuple(
        "distortion" if f.name == "dist" else f.name for f in fields(SimCamera)[1:]
    ),
    # ``photo: true`` takes every default of ``slidecal.mocks.render.Photo``; a mapping sets some
    "simulation.cameras.*.photo": PHOTO_KEYS,
    "simulation.noise": ("robot_mm", "robot_deg"),
    "simulation.target_jitter": ("mm", "deg"),
    "simulation.kinematic_error": tuple(KINEMATIC_ERROR_DEFAULTS),
}

#: Keys of the cell file's ``plan:`` block, the planner's options (slidecal.routines.planner).
PLAN_KEYS = (
    "goal",
    "max_duration_s",
    "tilts_deg",
    "azimuths_deg",
    "standoff_factors",
    "step_mm",
    "margin_px",
    "depth_m",
    "corner_noise_px",
    "capture_s",
    "fx_px",
    "hfov_deg",
    "min_groups",
    "min_frames_per_group",
    "max_groups",
    "max_frames_per_group",
    "extend_max_s",
)
GOAL_KEYS = ("fx_rel_std", "hand_eye_rot_std_deg", "hand_eye_t_std_mm")
#: Largest tilt of the view against the board normal: the detector is tested to 40 deg.
MAX_TILT_DEG = 40.0
#: Corner noise assumed for the rendered simulated camera, with photograph-like imaging (what
#: the default cell's runs measure, docs/results/PLANNER.md) and for a real camera; a run that
#: misses its limits extends its plan with the noise it measured (docs/UNATTENDED.md).
SIM_CORNER_NOISE_PX = 0.03
PHOTO_CORNER_NOISE_PX = 0.043
REAL_CORNER_NOISE_PX = 0.1
#: The arm's accuracy (mm, deg per axis) a plan is predicted for unless the cell states more: the
#: level a solve learns of an industrial arm over a calibration's poses (docs/results/REALITY.md).
PLAN_ARM_NOISE = (0.15, 0.025)
#: Keys of the ``install:`` section (:class:`InstallSettings`).
INSTALL_KEYS = ("dir", "accept_drift", "retries")
#: ``cameras:`` keys with a field of their own in :class:`CellConfig` (not in ``rig_options``).
RIG_TYPED = ("driver", "reference", "list", "device_id")

#: ``plan:`` keys of earlier versions that no longer act, and what to write instead.
RETIRED_PLAN_KEYS = {
    "frames_per_group": "the planner chooses the frames of each group; bound them with "
    "min_frames_per_group and max_frames_per_group",
    "groups": "the planner chooses the groups; bound them with min_groups and max_groups",
    "tilt_deg": "the planner chooses among candidate tilts; give them as tilts_deg: [25]",
}


@dataclass(frozen=True)
class PlanGoal:
    """What the plan must achieve: one-sigma targets (None: none; the hand-eye's are roots of the
    covariance traces) and a time budget."""

    fx_rel_std: float | None = 5e-4
    hand_eye_rot_std_deg: float | None = 0.1
    hand_eye_t_std_mm: float | None = None
    max_duration_s: float = 60.0


@dataclass(frozen=True)
class PlanSettings:
    """The ``plan:`` section, the planner's options (docstring of slidecal.routines.planner);
    ``K`` (3, 3) px and ``dist`` (5,) the nominal reference camera (from ``fx_px``, None: the
    simulated camera's data sheet or a nominal one); ``standoffs_m`` the candidate standoffs,
    ``standoff_factors`` times ``approximate.standoff_m``, metres."""

    goal: PlanGoal
    K: np.ndarray
    dist: np.ndarray
    fx_px: float | None
    tilts_deg: tuple[float, ...]
    azimuths_deg: tuple[float, ...]
    standoff_factors: tuple[float, ...]
    standoffs_m: tuple[float, ...]
    step_mm: tuple[float, ...]
    margin_px: float
    depth_m: tuple[float, float]
    corner_noise_px: float
    capture_s: float
    min_groups: int
    min_frames_per_group: int
    max_groups: int
    max_frames_per_group: int
    extend_max_s: float
    #: the arm's accuracy (mm, deg per axis) to predict for; None: ``arm_noise``'s default
    #: (a run's extension sets what it learned)
    robot_noise: tuple[float, float] | None = None
    #: (mm, deg) of each of the arm's error sources a run's solve learned
    #: (``RobotAccuracy.levels``); None: every source at ``robot_noise``
    robot_levels: Mapping[str, tuple[float, float]] | None = None


def _number_list(f: Fields, key: str, default: Sequence[float]) -> tuple[float, ...]:
    v = f.get(key, list(default))
    if not isinstance(v, list) or not v:
        raise f.error(key, f"must be a non-empty list of numbers, got {v!r}")
    out = []
    for x in v:
        if isinstance(x, bool) or not isinstance(x, int | float) or not np.isfinite(x):
            raise f.error(key, f"must hold finite numbers only, got {x!r}")
        out.append(float(x))
    return tuple(out)


def _plan(
    f: Fields, standoff_m: float, spec: CameraSpec, sim: SimulationConfig | None, lens: str
) -> PlanSettings:
    """The ``plan:`` section (``spec``: the reference camera, ``lens`` the lens model solved for:
    a simulated camera's data sheet of another model is not used); errors name the field."""
    f.only(PLAN_KEYS)
    gf = f.section("goal", GOAL_KEYS)
    defaults = {} if gf.data else {"fx_rel_std": 5e-4, "hand_eye_rot_std_deg": 0.1}
    vals = {k: gf.number(k, positive=True) if gf.has(k) else defaults.get(k) for k in GOAL_KEYS}
    goal = PlanGoal(**vals, max_duration_s=f.number("max_duration_s", 60.0, positive=True))
    if all(v is None for v in vals.values()):
        raise gf.error(None, f"names no goal; give at least one of {list(GOAL_KEYS)}")
    tilts = _number_list(f, "tilts_deg", (15.0, 25.0, 35.0))
    if any(not 0.0 < t <= MAX_TILT_DEG for t in tilts):
        raise f.error(
            "tilts_deg",
            f"must be in (0, {MAX_TILT_DEG:g}] deg: steeper views lose corners, untilted ones "
            "make the hand-eye translation unobservable",
        )
    az = _number_list(f, "azimuths_deg", tuple(float(a) for a in range(0, 360, 45)))
    factors = _number_list(f, "standoff_factors", (1.0,))
    if any(not 0.2 <= x <= 5.0 for x in factors):
        raise f.error("standoff_factors", "must be between 0.2 and 5 (times standoff_m)")
    steps = _number_list(f, "step_mm", (40.0, 80.0))
    if any(s <= 0 for s in steps):
        raise f.error("step_mm", "must be positive lengths in millimetres")
    standoffs = tuple(standoff_m * x for x in factors)
    depth = f.array("depth_m", (2,), [0.4 * min(standoffs), 1.8 * max(standoffs)])
    if not 0 < depth[0] < depth[1]:
        raise f.error("depth_m", "must be [near, far] with 0 < near < far (metres)")
    cam = None if sim is None else next((c for c in sim.cameras if c.name == spec.name), None)
    noise = REAL_CORNER_NOISE_PX if sim is None else SIM_CORNER_NOISE_PX
    if cam is not None and cam.photo is not None:
        noise = PHOTO_CORNER_NOISE_PX
    noise = f.number("corner_noise_px", noise, positive=True)
    fx = _nominal_fx(f, spec)
    if fx is not None:
        w, h = spec.width, spec.height
        K = np.array([[fx, 0.0, (w - 1) / 2.0], [0.0, fx, (h - 1) / 2.0], [0.0, 0.0, 1.0]])
        dist = zero_distortion(lens)
    elif cam is not None:  # a simulated camera's data sheet, its lens if of the model solved for
        K, dist = np.asarray(cam.K, float).copy(), np.asarray(cam.dist, float).copy()
        dist = dist if distortion_model(dist) == lens else zero_distortion(lens)
    else:
        K, dist = nominal_K((spec.width, spec.height)), zero_distortion(lens)
    min_groups = f.integer("min_groups", 3, minimum=2)
    min_frames = f.integer("min_frames_per_group", 3, minimum=2)
    max_groups = f.integer("max_groups", 6, minimum=min_groups)
    max_frames = f.integer("max_frames_per_group", 8, minimum=min_frames)
    return PlanSettings(
        goal=goal,
        K=K,
        dist=dist,
        fx_px=fx,
        tilts_deg=tilts,
        azimuths_deg=az,
        standoff_factors=factors,
        standoffs_m=standoffs,
        step_mm=steps,
        margin_px=f.number("margin_px", 20.0, minimum=0.0),
        depth_m=(float(depth[0]), float(depth[1])),
        corner_noise_px=noise,
        capture_s=f.number("capture_s", 0.05, minimum=0.0),
        min_groups=min_groups,
        min_frames_per_group=min_frames,
        max_groups=max_groups,
        max_frames_per_group=max_frames,
        extend_max_s=f.number("extend_max_s", 60.0, minimum=0.0),
    )


def _nominal_fx(f: Fields, spec: CameraSpec) -> float | None:
    """``fx_px`` (or from ``hfov_deg``) of the reference camera; None when neither is given."""
    if f.has("fx_px") and f.has("hfov_deg"):
        raise f.error("hfov_deg", "is given with fx_px; give one of them")
    if f.has("fx_px"):
        return f.number("fx_px", positive=True)
    if not f.has("hfov_deg"):
        return None
    hfov = f.number("hfov_deg", positive=True)
    if hfov >= 170:
        raise f.error("hfov_deg", f"is {hfov}; a pinhole camera has less than 170 deg")
    return float((spec.width / 2.0) / np.tan(np.radians(hfov) / 2.0))


def _plan_to_dict(p: PlanSettings) -> dict[str, Any]:
    """The ``plan:`` section of ``p``, every value explicit."""
    goal = {k: getattr(p.goal, k) for k in GOAL_KEYS if getattr(p.goal, k) is not None}
    out: dict[str, Any] = {"goal": goal, "max_duration_s": p.goal.max_duration_s}
    for k in PLAN_KEYS:
        v = getattr(p, k, None)
        if k not in out and v is not None:
            out[k] = list(v) if isinstance(v, tuple) else v
    return out


@dataclass(frozen=True)
class InstallSettings:
    """The ``install:`` section: the install store (None: none), whether a drifted result is
    installed, captures tried again per pose (None: the run's default)."""

    dir: str | None = None
    accept_drift: bool = False
    retries: int | None = None


@dataclass(frozen=True)
class RobotConfig:
    """The ``robot:`` section. ``tcp`` (4, 4) T_flange_tcp or None; workspace box (3,) each,
    base frame, metres (None: unbounded); ``start_pose`` (4, 4) T_base_tool and ``start_q``
    (6,) rad (simulated arm); ``limits``: the simulated arm's limits (``robot.limits``);
    ``ur_options``: the UR driver's ``take_control`` and payload keywords
    (``slidecal.drivers.ur.cell_options``)."""

    driver: str = "simulated"
    host: str | None = None
    model: str = "UR5e"
    tcp: np.ndarray | None = None
    speed_mps: float = 0.1
    accel_mps2: float = 0.5
    settle_s: float = 0.5
    start_pose: np.ndarray | None = None
    workspace_min_m: np.ndarray | None = None
    workspace_max_m: np.ndarray | None = None
    start_q: np.ndarray | None = None
    limits: dict[str, float] = field(default_factory=dict)
    ur_options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SimulationConfig:
    """The ``simulation:`` section: the truth of a simulated cell.

    ``cameras``: :class:`~slidecal.mocks.camera.SimCamera` per name; ``T_hand_eye``, ``T_target``,
    ``rig`` (4, 4): the reference camera's hand-eye, the target pose and ``T_<name>_<reference>``;
    robot noise per axis (metres, degrees); ``target_jitter_mm``/``_deg``: one-sigma per axis of
    the target's pose drawn anew per run; ``kinematic_error``: the arm's systematic error
    (:class:`~slidecal.mocks.robot.KinematicError` sizes; None: the nominal model);
    ``board_bow_mm``: the board's true bow along x and y.
    """

    seed: int
    cameras: tuple[SimCamera, ...]
    T_hand_eye: np.ndarray
    T_target: np.ndarray
    rig: dict[str, np.ndarray]
    robot_noise_m: float = 5e-5
    robot_noise_deg: float = 0.005
    target_jitter_mm: float = 0.0
    target_jitter_deg: float = 0.0
    kinematic_error: dict[str, float] | None = None
    board_bow_mm: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class CellConfig:
    """A validated cell description (docs/FORMATS.md). ``sha256``: of the file's bytes;
    ``camera_options``: per camera its ``cameras.list`` driver options; ``rig_options``: the
    ``cameras:`` section's driver options."""

    source: str
    mount: str
    robot: RobotConfig
    camera_driver: str
    cameras: tuple[CameraSpec, ...]
    camera_options: dict[str, dict[str, Any]]
    reference_camera: str
    target: Target
    approx_T_hand_eye: np.ndarray
    approx_T_target: np.ndarray
    standoff_m: float
    simulation: SimulationConfig | None
    plan: PlanSettings
    options: ModelOptions
    limits: Limits = field(default_factory=Limits)
    install: InstallSettings = field(default_factory=InstallSettings)
    rig_options: dict[str, Any] = field(default_factory=dict)
    sha256: str | None = None
    device_id: str | None = None

    @property
    def simulated(self) -> bool:
        """True when no real robot moves (``robot.driver: simulated``)."""
        return self.robot.driver == "simulated"

    def session_fields(self) -> dict[str, Any]:
        """What a session records about its cell (``cell``, ``cell_sha256``, the drivers)."""
        out: dict[str, Any] = {"cell": self.source}
        if self.sha256 is not None:
            out["cell_sha256"] = self.sha256
        out["robot_driver"] = self.robot.driver
        out["camera_driver"] = self.camera_driver
        return out


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None):
    """Read and validate a cell file (None: the packaged default simulated cell); ``overrides``:
    nested values merged over it, e.g. ``{"simulation": {"seed": 3}}``."""
    if path is None:
        return load_packaged_cell(DEFAULT_CELL, overrides)
    path = Path(path)
    data = load_yaml(path, "cell file")
    sha = hashlib.sha256(path.read_bytes()).hexdigest()
    return config_from_dict(_merge(data, overrides or {}), path.name, sha256=sha)


def load_packaged_cell(name: str, overrides: Mapping[str, Any] | None = None) -> CellConfig:
    """A cell shipped in ``slidecal.mocks`` (``default_cell.yaml``, ``oak_cell.yaml``,
    ``eye_to_hand_cell.yaml``)."""
    ref = resources.files("slidecal.mocks").joinpath(name)
    if not name.endswith(".yaml") or not ref.is_file():
        raise InputError(f"no packaged cell named {name!r}; see slidecal/mocks/*.yaml")
    raw = ref.read_bytes()
    data = parse_yaml(raw.decode("utf-8"), name)
    sha = hashlib.sha256(raw).hexdigest()
    return config_from_dict(_merge(data, overrides or {}), name, sha256=sha)


def _merge(base: Any, over: Mapping[str, Any]) -> Any:
    if not isinstance(base, Mapping):
        return base
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def config_from_dict(data: Any, source: str = "cell.yaml", sha256: str | None = None) -> CellConfig:
    """Validate a parsed cell description; errors name ``source: field``."""
    f = Fields(data, source).only(CELL_KEYS[""])
    if f.has("format") and f.get("format") != CELL_FORMAT:
        raise f.error("format", f"is {f.get('format')!r}; expected {CELL_FORMAT!r}")
    mount = f.choice("mount", CELL_MOUNTS, "eye_in_hand")
    robot = _robot(f.section("robot", CELL_KEYS["robot"]))
    simulated = robot.driver == "simulated"
    # a simulated board is exactly as described unless the cell gives its tolerance or bows it
    bowed = simulated and f.section("simulation").has("board_bow_mm")
    target = target_from_dict(f.require("target"), source, exact_by_default=simulated and not bowed)

    sim = _simulation(f.section("simulation"), mount) if simulated else None
    cam_f = f.section("cameras", CELL_KEYS["cameras"])
    driver = cam_f.choice("driver", CAMERA_DRIVERS, "simulated")
    if driver == "simulated" and sim is None:
        raise cam_f.error(
            "driver", "is 'simulated' but the robot is real; name the real cameras (oak or uvc)"
        )
    if driver != "simulated" and robot.driver == "simulated":
        raise cam_f.error(
            "driver",
            f"is {driver!r} with a simulated robot; use driver: simulated, or a real "
            "robot (robot.driver: ur)",
        )
    if driver == "simulated" and cam_f.has("list"):
        raise cam_f.error(
            "list", "is for real cameras; simulated cameras are described in simulation.cameras"
        )
    device_id = cam_f.string("device_id") if cam_f.has("device_id") else None
    if device_id is not None and driver != "oak":
        raise cam_f.error("device_id", f"is an OAK option; the driver here is {driver!r}")
    specs, cam_opts = _cameras(cam_f, driver, sim)
    names = [c.name for c in specs]
    reference = cam_f.camera("reference", names)
    if sim is not None:
        missing = [n for n in names if n != reference and n not in sim.rig]
        if missing:
            raise InputError(
                f"gives no T_{missing[0]}_{reference}; add simulation.rig.{missing[0]}",
                where=f"{source}: simulation.rig",
            )
        extra = [n for n in sim.rig if n not in names or n == reference]
        if extra:
            raise InputError(
                f"{extra[0]!r} is not a non-reference camera of this cell; cameras are {names}",
                where=f"{source}: simulation.rig.{extra[0]}",
            )

    approx_he, approx_target, standoff = _approximate(f, mount)
    plan = f.section("plan")
    for key, why in RETIRED_PLAN_KEYS.items():
        if key in plan.data:
            raise plan.error(key, f"no longer acts: {why}")
    options = options_from_dict(f.get("options", {}), source)
    lens = options.lens
    plan_settings = _plan(plan, standoff, specs[names.index(reference)], sim, lens)
    limits = limits_from_dict(f.get("limits"), source)
    return CellConfig(
        source=source,
        mount=mount,
        robot=robot,
        camera_driver=driver,
        cameras=specs,
        camera_options=cam_opts,
        reference_camera=reference,
        target=target,
        approx_T_hand_eye=approx_he,
        approx_T_target=approx_target,
        standoff_m=standoff,
        simulation=sim,
        plan=plan_settings,
        options=options,
        limits=limits,
        install=_install(f.section("install")),
        rig_options={k: v for k, v in cam_f.data.items() if k not in RIG_TYPED},
        sha256=sha256,
        device_id=device_id,
    )


def _install(f: Fields) -> InstallSettings:
    for k in f.data:
        if k not in INSTALL_KEYS:
            raise f.error(str(k), f"is not an install field; the fields are {list(INSTALL_KEYS)}")
    return InstallSettings(
        dir=f.string("dir") if f.has("dir") else None,
        accept_drift=f.boolean("accept_drift", False),
        retries=f.integer("retries", minimum=0) if f.has("retries") else None,
    )


def config_to_dict(cfg: CellConfig) -> dict[str, Any]:
    """A validated real cell's file but ``cameras:`` (the inverse of :func:`config_from_dict`):
    every value explicit, transforms as ``{R, t_m}``; a simulated cell's truth is not written."""
    r = cfg.robot
    robot: dict[str, Any] = {"driver": r.driver}
    if r.host is not None:
        robot["host"] = r.host
    robot.update(model=r.model, speed_mps=r.speed_mps, accel_mps2=r.accel_mps2, settle_s=r.settle_s)
    for key, T in (("tcp", r.tcp), ("start_pose", r.start_pose)):
        if T is not None:
            robot[key] = ur_pose_from_T(T)
    if r.start_q is not None:
        robot["start_q"] = r.start_q.tolist()
    if r.workspace_min_m is not None and r.workspace_max_m is not None:
        robot["workspace"] = {
            "min_m": r.workspace_min_m.tolist(),
            "max_m": r.workspace_max_m.tolist(),
        }
    if r.limits:
        robot["limits"] = dict(r.limits)
    for key in ("take_control", "upper_range_registers"):
        if r.ur_options.get(key):
            robot[key] = True
    if "payload_kg" in r.ur_options:
        robot["payload"] = {"mass_kg": r.ur_options["payload_kg"]}
        if r.ur_options["payload_cog_m"] is not None:
            robot["payload"]["cog_m"] = list(r.ur_options["payload_cog_m"])
    he_key, tg_key = POSE_NAMES[cfg.mount]
    out: dict[str, Any] = {
        "format": CELL_FORMAT,
        "mount": cfg.mount,
        "robot": robot,
        "target": target_to_dict(cfg.target),
        "approximate": {
            tg_key: transform_to_dict(cfg.approx_T_target),
            he_key: transform_to_dict(cfg.approx_T_hand_eye),
            "standoff_m": cfg.standoff_m,
        },
    }
    out["plan"] = _plan_to_dict(cfg.plan)
    out["options"] = options_to_dict(cfg.options)
    out["limits"] = limits_to_dict(cfg.limits)
    out["install"] = {k: v for k, v in asdict(cfg.install).items() if v is not None}
    return out


def limits_to_dict(limits: Limits) -> dict[str, Any]:
    """The ``limits:`` section of ``limits`` (as a session records it)."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(limits).items()}


def _refuse_other_mount(f: Fields, mount: str) -> None:
    """A hand-eye or target pose named for the other mount is a user's mistake: say so."""
    other = "eye_to_hand" if mount == "eye_in_hand" else "eye_in_hand"
    for mine, theirs in zip(POSE_NAMES[mount], POSE_NAMES[other], strict=True):
        if theirs in f.data:
            raise f.error(
                theirs,
                f"is a pose of an {other} cell but this cell is {mount} (mount); give {mine}, "
                "or set mount",
            )


def _approximate(f: Fields, mount: str) -> tuple[np.ndarray, np.ndarray, float]:
    """The ``approximate:`` section, used as given (simulated cells too: never the truth)."""
    app = f.section("approximate")
    _refuse_other_mount(app, mount)
    app.only(CELL_KEYS[f"approximate.{mount}"])
    he_key, tg_key = POSE_NAMES[mount]
    if not app.has(tg_key):
        raise app.error(
            tg_key, "is missing; give the rough target pose (R, rpy_deg or q_wxyz; t_m or t_mm)"
        )
    approx_target = transform_from_dict(app, tg_key)
    if app.has(he_key):
        approx_he = transform_from_dict(app, he_key)
    elif mount == "eye_in_hand":
        approx_he = np.eye(4)  # camera looking along the tool's z axis at the flange
    else:
        raise app.error(he_key, "is missing; give the rough camera pose in the base frame")
    standoff = app.number("standoff_m", 0.5, positive=True, maximum=20.0)
    return approx_he, approx_target, standoff


def _robot(f: Fields) -> RobotConfig:
    driver = f.choice("driver", ROBOT_DRIVERS, "simulated")
    host = f.get("host")
    if driver == "ur" and not host:
        raise f.error("host", "is missing; driver 'ur' needs the controller's address")
    if host is not None and (not isinstance(host, str) or not host.strip()):
        raise f.error("host", f"must be a host name or IP address string, got {host!r}")
    if host is not None and driver != "ur":
        raise f.error("host", "is given for a simulated robot; set driver: ur or remove host")
    model = f.string("model", "UR5e")
    try:
        urk.model_by_name(model)
    except InputError as e:
        raise f.error("model", str(e)) from None
    speed = f.number("speed_mps", 0.1, positive=True)
    if speed > 1.0:
        raise f.error("speed_mps", f"is {speed} m/s; calibration moves must be slow (<= 1.0)")
    accel = f.number("accel_mps2", 0.5, positive=True)
    if accel > 2.5:
        raise f.error("accel_mps2", f"is {accel} m/s2; use at most 2.5 for calibration moves")
    settle = f.number("settle_s", 0.5, minimum=0.0, maximum=60.0)
    wmin = wmax = None
    if f.has("workspace"):
        ws = f.section("workspace", CELL_KEYS["robot.workspace"])
        wmin, wmax = ws.array("min_m", (3,)), ws.array("max_m", (3,))
        if np.any(wmin >= wmax):
            raise ws.error("max_m", "must be larger than min_m on every axis")
    start_q = None
    if f.has("start_q"):
        start_q = f.array("start_q", (6,))
        if np.any(np.abs(start_q) > 2 * np.pi + 1e-9):
            raise f.error("start_q", "has a joint beyond +-2 pi; give the joints in radians")
    for key in ("start_q", "start_pose"):
        if f.has(key) and driver != "simulated":
            raise f.error(key, "is for the simulated arm; the real arm starts where it is")
    lf = f.section("limits", CELL_KEYS["robot.limits"])
    limits = {
        k: lf.number(k, positive=k != "z_min_m") for k in CELL_KEYS["robot.limits"] if lf.has(k)
    }
    return RobotConfig(
        driver=driver,
        host=host,
        model=model,
        tcp=ur_pose_field(f, "tcp") if f.has("tcp") else None,
        speed_mps=speed,
        accel_mps2=accel,
        settle_s=settle,
        start_pose=ur_pose_field(f, "start_pose") if f.has("start_pose") else None,
        workspace_min_m=wmin,
        workspace_max_m=wmax,
        start_q=start_q,
        limits=limits,
        ur_options=cell_options(f.data),
    )


def _preset_cameras(preset: str) -> tuple[list[SimCamera], dict[str, np.ndarray]]:
    if preset == "r1":
        return [simcam.single_camera("cam")], {}
    ext = simcam.oak_d_like_extrinsics()  # T_<name>_left
    return simcam.oak_d_like(), {n: T for n, T in ext.items() if n != "left"}


def _sim_camera(c: Fields, name: str, base: SimCamera | None) -> SimCamera:
    """One ``simulation.cameras.<name>`` entry, over the preset's camera of that name."""
    if base is None:
        for key in ("width", "height", "K"):
            if not c.has(key):
                raise c.error(key, f"is missing; camera {name!r} is not in the preset")
    K = c.array("K", (3, 3)) if c.has("K") else base.K  # type: ignore[union-attr]
    if (
        K[2, 2] != 1.0
        or K[1, 0] != 0
        or K[2, 0] != 0
        or K[2, 1] != 0
        or K[0, 0] <= 0
        or K[1, 1] <= 0
    ):
        raise c.error("K", "must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    dist = (
        c.distortion("distortion")
        if c.has("distortion")
        else (base.dist if base is not None else np.zeros(5))
    )
    values: dict[str, Any] = {"K": K, "dist": dist}
    for key in ("width", "height"):
        if c.has(key):
            values[key] = c.integer(key, minimum=1, maximum=100_000)
    for key, lo, hi in (
        ("blur_sigma_px", 0.0, 20.0),
        ("noise_std", 0.0, 100.0),
        ("exposure", 1e-6, 100.0),
        ("vignetting", 0.0, 1.0),
    ):
        if c.has(key):
            values[key] = c.number(key, minimum=lo, maximum=hi)
    if c.has("colour"):
        values["colour"] = c.boolean("colour")
    if c.has("photo"):
        values["photo"] = _photo(c)
    if base is not None:
        return replace(base, **values)
    return SimCamera(name=name, **values)


def _photo(c: Fields) -> Photo | None:
    """``simulation.cameras.<name>.photo``: true (the defaults), false (the clean renderer) or a
    mapping of :class:`~slidecal.mocks.render.Photo` fields over the defaults."""
    if isinstance(c.data.get("photo"), bool):
        return Photo() if c.boolean("photo") else None
    if not isinstance(c.data.get("photo"), Mapping):
        raise c.error("photo", "must be true, false or a mapping of photo parameters")
    pf = c.section("photo", CELL_KEYS["simulation.cameras.*.photo"])
    defaults = Photo()
    values: dict[str, Any] = {}
    for name in pf.data:
        default = getattr(defaults, name)
        if isinstance(default, bool):
            values[name] = pf.boolean(name)
        elif name in ("jpeg_quality", "glare_spots"):
            values[name] = pf.integer(name, minimum=0, maximum=100)
        elif name == "focus_distance_m":
            values[name] = None if pf.data[name] is None else pf.number(name, minimum=1e-3)
        elif name in ("chromatic_red", "chromatic_blue"):
            values[name] = pf.number(name, minimum=-0.05, maximum=0.05)
        elif name in ("vignetting", "gradient", "glare_strength"):
            values[name] = pf.number(name, minimum=0.0, maximum=1.0)
        else:  # aperture_mm, pixel_pitch_um, full_well_e, glare_radius
            values[name] = pf.number(name, minimum=0.0, maximum=1e6)
    return Photo(**values)


def _simulation(f: Fields, mount: str) -> SimulationConfig:
    _refuse_other_mount(f, mount)
    he_key, tg_key = POSE_NAMES[mount]
    f.only((*CELL_KEYS["simulation"], he_key, tg_key))
    seed = f.integer("seed", 0, minimum=0)
    preset = f.choice("camera_preset", CAMERA_PRESETS, "r1") if f.has("camera_preset") else None
    cams: list[SimCamera] = []
    rig: dict[str, np.ndarray] = {}
    if preset is not None:
        cams, rig = _preset_cameras(preset)
    cf = f.section("cameras")
    for name in cf.cameras():
        c = cf.section(name, CELL_KEYS["simulation.cameras.*"])
        base = next((x for x in cams if x.name == name), None)
        new = _sim_camera(c, name, base)
        cams = [x for x in cams if x.name != name] + [new]
    if not cams:
        cams, rig = _preset_cameras("r1")
    rf = f.section("rig")
    for name in rf.data:
        rig[str(name)] = transform_from_dict(rf, str(name))
    for key in (he_key, tg_key):
        if not f.has(key):
            raise f.error(key, f"is missing; the simulated cell needs the true {key}")
    nf = f.section("noise", CELL_KEYS["simulation.noise"])
    jf = f.section("target_jitter", CELL_KEYS["simulation.target_jitter"])
    kinematic_error = None
    if f.has("kinematic_error"):
        kf = f.section("kinematic_error", CELL_KEYS["simulation.kinematic_error"])
        kinematic_error = {
            k: kf.number(k, v, minimum=0.0, maximum=1000.0)
            for k, v in KINEMATIC_ERROR_DEFAULTS.items()
        }
    return SimulationConfig(
        seed=seed,
        cameras=tuple(cams),
        T_hand_eye=transform_from_dict(f, he_key),
        T_target=transform_from_dict(f, tg_key),
        rig=rig,
        robot_noise_m=nf.number("robot_mm", 0.05, minimum=0.0, maximum=100.0) / 1000.0,
        robot_noise_deg=nf.number("robot_deg", 0.005, minimum=0.0, maximum=10.0),
        target_jitter_mm=jf.number("mm", 0.0, minimum=0.0, maximum=1000.0),
        target_jitter_deg=jf.number("deg", 0.0, minimum=0.0, maximum=90.0),
        kinematic_error=kinematic_error,
        board_bow_mm=_board_bow(f),
    )


def _board_bow(f: Fields) -> tuple[float, float]:
    """``simulation.board_bow_mm``: two numbers (mm) within +-20, or (0, 0) when absent."""
    if not f.has("board_bow_mm"):
        return (0.0, 0.0)
    bow = f.array("board_bow_mm", (2,))
    if np.any(np.abs(bow) > 20.0):
        raise f.error(
            "board_bow_mm",
            f"is {bow.tolist()} mm; a board bows by tenths of a millimetre (at most 20 mm here): "
            "give the bow along the board's x and y in mm",
        )
    return (float(bow[0]), float(bow[1]))


def _cameras(
    f: Fields, driver: str, sim: SimulationConfig | None
) -> tuple[tuple[CameraSpec, ...], dict[str, dict[str, Any]]]:
    if driver == "simulated":
        assert sim is not None
        specs = tuple(CameraSpec(c.name, c.width, c.height) for c in sim.cameras)
        return specs, {c.name: {} for c in sim.cameras}
    if not f.has("list"):
        raise f.error(
            "list", f"is missing; driver {driver!r} needs a list of {{name, width, height}} cameras"
        )
    specs = []
    opts: dict[str, dict[str, Any]] = {}
    keys = CELL_KEYS[f"cameras.list[].{driver}"]
    for cf in f.entries("list", keys, non_empty=True, hint="camera {name, width, height}"):
        specs.append(camera_spec(cf, list(opts)))
        if driver == "oak":
            if not cf.has("socket"):
                raise cf.error("socket", "is missing; an OAK camera needs its socket (CAM_A ..)")
            if not OAK_SOCKET.fullmatch(cf.string("socket")):
                raise cf.error("socket", f"is {cf.get('socket')!r}; use CAM_A .. CAM_H")
            if cf.has("colour"):
                cf.boolean("colour")
        else:
            if cf.has("fourcc") and len(cf.string("fourcc")) != 4:
                raise cf.error("fourcc", "must be 4 characters (e.g. MJPG)")
            if cf.has("exposure"):
                cf.number("exposure")
            if cf.has("drop_frames"):
                cf.integer("drop_frames", minimum=0, maximum=100)
        opts[specs[-1].name] = {
            k: v for k, v in cf.data.items() if k not in ("name", "width", "height")
        }
    if driver == "oak":
        socks = [o["socket"] for o in opts.values()]
        dup = next((s for s in socks if socks.count(s) > 1), None)
        if dup is not None:
            raise f.error("list", f"gives socket {dup} to two cameras; each socket is one camera")
    return tuple(specs), opts

"""The cell description (``cell.yaml``): what robot, which cameras, how mounted, which target.

THE ROBOT NEVER MOVES unless the file names real hardware: ``robot.driver: ur`` with a
``host``. Without a file, the packaged simulated cell (``mocks/default_cell.yaml``) is used.

Layout (every field but ``target`` has a default)::

    mount: eye_in_hand             # eye_in_hand (camera on the tool) | eye_to_hand
    robot:
      driver: simulated            # simulated | ur
      host: 192.168.1.10           # ur only: the controller's address
      model: UR5e                  # UR3e | UR5e | UR10e | UR16e
      tcp: [0, 0, 0, 0, 0, 0]      # TCP on the flange as a UR pose (what the controller uses)
      speed_mps: 0.10
      accel_mps2: 0.5
      settle_s: 0.5
      start_pose: [x, y, z, rx, ry, rz]   # simulated only: where the arm starts
      workspace: {min_m: [x, y, z], max_m: [x, y, z]}   # TCP box (base frame) plans must keep
    cameras:
      driver: simulated            # simulated | oak | uvc
      reference: left              # rigs: the camera the others are expressed against
      list:                        # oak / uvc: name, width, height and driver options
        - {name: left, width: 1280, height: 800, socket: CAM_B}
    target: {kind: charuco, squares_x: 11, squares_y: 8, square_size_m: 0.03,
             marker_size_m: 0.022, dictionary: DICT_5X5_100}   # as in session.yaml
    approximate:                   # rough geometry for planning (a tape measure is enough)
      T_base_board: {rpy_deg: [180, 0, 0], t_m: [0.3, 0.07, 0.0]}   # eye_in_hand
      T_tool_cam: {rpy_deg: [0, 0, 90], t_m: [0.03, -0.06, 0.045]}  # eye_in_hand
      # eye_to_hand: T_base_cam and T_tool_board
      standoff_m: 0.5              # camera-to-board distance the plan keeps
    simulation:                    # simulated cells only: the truth
      seed: 0
      camera_preset: r1            # r1 | oak_d_like (fills cameras and rig below)
      cameras: {cam: {width, height, K, distortion, blur_sigma_px, noise_std, exposure}}
      T_tool_cam: {rpy_deg | R, t_m}      # or T_base_cam (eye_to_hand); the reference camera
      T_base_board: {rpy_deg | R, t_m}    # or T_tool_board (eye_to_hand)
      rig: {right: {R, t_m}}              # T_<name>_<reference> of the other cameras
      noise: {robot_mm: 0.05, robot_deg: 0.005}
      target_jitter: {mm: 2.0, deg: 0.5}  # the target's true pose moves this much per seed
    plan: {frames_per_group: 5, tilt_deg: 25, step_mm: [40, 80]}
    options: {skew: false, unit_aspect: false, distortion: [true, true, true, true, false],
              robot_noise_mm: 0.05, robot_noise_deg: 0.005}   # robot: 1-sigma pose error per axis

Every error names the file and the field, says what is wrong and how to fix it, in one line.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.drivers.ur_pose import T_from_ur_pose
from slidecal.routines.session import (
    Fields,
    as_array,
    load_yaml,
    options_from_dict,
    target_from_dict,
    transform_from_dict,
)
from slidecal.solver.errors import InputError
from slidecal.solver.problem import CameraSpec, ModelOptions, Target

ROBOT_DRIVERS = ("simulated", "ur")
CAMERA_DRIVERS = ("simulated", "oak", "uvc")
CELL_MOUNTS = ("eye_in_hand", "eye_to_hand")
CAMERA_PRESETS = ("r1", "oak_d_like")
DEFAULT_CELL = "default_cell.yaml"


@dataclass(frozen=True)
class RobotConfig:
    """The ``robot:`` section. ``tcp`` (4, 4) T_flange_tcp or None; workspace box (3,) each,
    base frame, metres (None: unbounded); ``start_pose`` (4, 4) T_base_tool (simulated)."""

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
    raw: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SimCameraConfig:
    """One simulated camera's truth: ``K`` (3, 3) px, ``distortion`` (5,) OpenCV order."""

    name: str
    width: int
    height: int
    K: np.ndarray
    distortion: np.ndarray
    blur_sigma_px: float = 0.6
    noise_std: float = 2.0
    exposure: float = 1.0
    colour: bool = False


@dataclass(frozen=True)
class SimulationConfig:
    """The ``simulation:`` section: the truth of a simulated cell.

    ``T_hand_eye`` (4, 4): ``T_tool_cam`` (eye-in-hand) or ``T_base_cam`` (eye-to-hand) of the
    reference camera; ``T_target`` (4, 4): ``T_base_board`` or ``T_tool_board``; ``rig``:
    ``T_<name>_<reference>`` (4, 4) per other camera. Noise: robot position std per axis
    (metres) and rotation std per axis (degrees). ``target_jitter_mm``/``_deg``: the target is
    set up anew for each run: its true pose moves by this one-sigma amount per axis, drawn from
    the run's seed (so a renderer's per-corner artefacts do not repeat from seed to seed).
    """

    seed: int
    cameras: tuple[SimCameraConfig, ...]
    T_hand_eye: np.ndarray
    T_target: np.ndarray
    rig: dict[str, np.ndarray]
    robot_noise_m: float = 5e-5
    robot_noise_deg: float = 0.005
    target_jitter_mm: float = 0.0
    target_jitter_deg: float = 0.0


@dataclass(frozen=True)
class CellConfig:
    """A validated cell description (see the module docstring)."""

    source: str
    mount: str
    robot: RobotConfig
    camera_driver: str
    cameras: tuple[CameraSpec, ...]
    camera_options: dict[str, dict[str, Any]]
    reference_camera: str
    target: Target
    target_dict: dict[str, Any]
    approx_T_hand_eye: np.ndarray
    approx_T_target: np.ndarray
    standoff_m: float
    simulation: SimulationConfig | None
    plan: dict[str, Any]
    options: ModelOptions
    raw: dict[str, Any]

    @property
    def simulated(self) -> bool:
        """True when no real robot moves (``robot.driver: simulated``)."""
        return self.robot.driver == "simulated"


def load_config(path: str | Path | None = None, overrides: Mapping[str, Any] | None = None):
    """Read and validate a cell file; ``None``: the packaged default simulated cell.

    ``overrides``: nested values merged over the file (e.g. ``{"simulation": {"seed": 3}}``).
    """
    if path is None:
        return load_packaged_cell(DEFAULT_CELL, overrides)
    path = Path(path)
    data = load_yaml(path, "cell file")
    return config_from_dict(_merge(data, overrides or {}), path.name)


def load_packaged_cell(name: str, overrides: Mapping[str, Any] | None = None) -> CellConfig:
    """A cell shipped in ``slidecal.mocks`` (``default_cell.yaml``, ``oak_cell.yaml``,
    ``eye_to_hand_cell.yaml``)."""
    ref = resources.files("slidecal.mocks").joinpath(name)
    if not ref.is_file():
        raise InputError(f"no packaged cell named {name!r}; see slidecal/mocks/*.yaml")
    import yaml

    data = yaml.safe_load(ref.read_text(encoding="utf-8"))
    return config_from_dict(_merge(data, overrides or {}), name)


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


def config_from_dict(data: Any, source: str = "cell.yaml") -> CellConfig:
    """Validate a parsed cell description; errors name ``source: field``."""
    f = Fields(data, source)
    known = {
        "format",
        "mount",
        "robot",
        "cameras",
        "target",
        "approximate",
        "simulation",
        "plan",
        "options",
        "limits",  # the verdict's limits (routines/verdict.py: limits_from_dict)
        "install",  # the install store (routines/run.py: cell_install)
    }
    unknown = sorted(set(f.data) - known)
    if unknown:
        raise f.error(unknown[0], f"is not a cell field; the fields are {sorted(known)}")
    if f.has("format") and f.get("format") != "slidecal.cell/1":
        raise f.error("format", f"is {f.get('format')!r}; expected 'slidecal.cell/1'")
    mount = f.choice("mount", CELL_MOUNTS, "eye_in_hand")
    robot = _robot(f.sub("robot", required=False) or Fields({}, source, "robot"))
    target = target_from_dict(f.require("target"), source)
    from slidecal.routines.session import target_to_dict

    sim = None
    if robot.driver == "simulated":
        simf = f.sub("simulation", required=False) or Fields({}, source, "simulation")
        sim = _simulation(simf, mount)
    cam_f = f.sub("cameras", required=False) or Fields({}, source, "cameras")
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
    specs, cam_opts = _cameras(cam_f, driver, sim)
    names = [c.name for c in specs]
    reference = cam_f.string("reference", names[0])
    if reference not in names:
        raise cam_f.error("reference", f"{reference!r} is not a camera; cameras are {names}")
    if sim is not None:
        missing = [n for n in names if n != reference and n not in sim.rig]
        if missing:
            raise InputError(
                f"gives no T_{missing[0]}_{reference}; add simulation.rig.{missing[0]}",
                where=f"{source}: simulation.rig",
            )

    app = f.sub("approximate", required=False) or Fields({}, source, "approximate")
    he_key, tg_key = _names(mount)
    if app.has(tg_key):
        approx_target = transform_from_dict(app, tg_key)
    elif sim is not None:
        approx_target = sim.T_target
    else:
        raise app.error(tg_key, "is missing; give the rough target pose (R or rpy_deg, t_m)")
    if app.has(he_key):
        approx_he = transform_from_dict(app, he_key)
    elif sim is not None:
        approx_he = sim.T_hand_eye
    elif mount == "eye_in_hand":
        approx_he = np.eye(4)  # camera looking along the tool's z axis at the flange
    else:
        raise app.error(he_key, "is missing; give the rough camera pose in the base frame")
    standoff = app.number("standoff_m", 0.5, positive=True)
    plan = f.get("plan", {})
    if not isinstance(plan, Mapping):
        raise f.error("plan", "must be a mapping of plan options")
    options = options_from_dict(f.get("options", {}), source)
    return CellConfig(
        source=source,
        mount=mount,
        robot=robot,
        camera_driver=driver,
        cameras=specs,
        camera_options=cam_opts,
        reference_camera=reference,
        target=target,
        target_dict=target_to_dict(target),
        approx_T_hand_eye=approx_he,
        approx_T_target=approx_target,
        standoff_m=standoff,
        simulation=sim,
        plan=dict(plan),
        options=options,
        raw=dict(f.data),
    )


def _names(mount: str) -> tuple[str, str]:
    """Hand-eye and target-pose field names of a mount."""
    if mount == "eye_in_hand":
        return "T_tool_cam", "T_base_board"
    return "T_base_cam", "T_tool_board"


def _pose(f: Fields, key: str) -> np.ndarray | None:
    if not f.has(key):
        return None
    v = as_array(f.get(key), (-1,), f.where(key))
    if v.shape != (6,):
        raise f.error(key, f"has {v.size} numbers; a UR pose is [x, y, z, rx, ry, rz] (m, rad)")
    return T_from_ur_pose(v)


def _robot(f: Fields) -> RobotConfig:
    known = {
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
    }
    unknown = sorted(set(f.data) - known)
    if unknown:
        raise f.error(unknown[0], f"is not a robot field; the fields are {sorted(known)}")
    driver = f.choice("driver", ROBOT_DRIVERS, "simulated")
    host = f.get("host")
    if driver == "ur" and not host:
        raise f.error("host", "is missing; driver 'ur' needs the controller's address")
    if host is not None and not isinstance(host, str):
        raise f.error("host", f"must be a host name or IP address string, got {host!r}")
    model = f.string("model", "UR5e")
    from slidecal.drivers import ur_kinematics as urk

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
    settle = f.number("settle_s", 0.5, minimum=0.0)
    wmin = wmax = None
    ws = f.sub("workspace", required=False)
    if ws is not None:
        wmin, wmax = ws.array("min_m", (3,)), ws.array("max_m", (3,))
        if np.any(wmin >= wmax):
            raise ws.error("max_m", "must be larger than min_m on every axis")
    return RobotConfig(
        driver=driver,
        host=host,
        model=model,
        tcp=_pose(f, "tcp"),
        speed_mps=speed,
        accel_mps2=accel,
        settle_s=settle,
        start_pose=_pose(f, "start_pose"),
        workspace_min_m=wmin,
        workspace_max_m=wmax,
        raw=dict(f.data),
    )


def _preset_cameras(preset: str) -> tuple[list[SimCameraConfig], dict[str, np.ndarray]]:
    from slidecal.mocks import camera as simcam

    if preset == "r1":
        cams = [simcam.single_camera("cam")]
        rig: dict[str, np.ndarray] = {}
    else:
        cams = simcam.oak_d_like()
        ext = simcam.oak_d_like_extrinsics()  # T_<name>_left
        rig = {n: T for n, T in ext.items() if n != "left"}
    out = [
        SimCameraConfig(
            c.name,
            c.width,
            c.height,
            c.K,
            c.dist,
            c.blur_sigma_px,
            c.noise_std,
            c.exposure,
            c.colour,
        )
        for c in cams
    ]
    return out, rig


def _simulation(f: Fields, mount: str) -> SimulationConfig:
    seed = f.integer("seed", 0, minimum=0)
    preset = f.choice("camera_preset", CAMERA_PRESETS, "r1") if f.has("camera_preset") else None
    cams: list[SimCameraConfig] = []
    rig: dict[str, np.ndarray] = {}
    if preset is not None:
        cams, rig = _preset_cameras(preset)
    cf = f.sub("cameras", required=False)
    if cf is not None:
        for name in cf.data:
            c = cf.sub(str(name))
            assert c is not None
            base = next((x for x in cams if x.name == name), None)
            K = c.array("K", (3, 3)) if c.has("K") or base is None else base.K
            if K[2, 2] != 1.0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[0, 0] <= 0:
                raise c.error("K", "must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
            dist = (
                c.array("distortion", (5,))
                if c.has("distortion") or base is None
                else base.distortion
            )
            new = SimCameraConfig(
                str(name),
                c.integer("width", base.width if base else None, minimum=1),
                c.integer("height", base.height if base else None, minimum=1),
                K,
                dist,
                c.number("blur_sigma_px", base.blur_sigma_px if base else 0.6, minimum=0.0),
                c.number("noise_std", base.noise_std if base else 2.0, minimum=0.0),
                c.number("exposure", base.exposure if base else 1.0, positive=True),
                c.boolean("colour", base.colour if base else False),
            )
            cams = [x for x in cams if x.name != name] + [new]
    if not cams:
        cams, rig = _preset_cameras("r1")
    rf = f.sub("rig", required=False)
    if rf is not None:
        for name in rf.data:
            rig[str(name)] = transform_from_dict(rf, str(name))
    he_key, tg_key = _names(mount)
    T_he = transform_from_dict(f, he_key) if f.has(he_key) else None
    T_tg = transform_from_dict(f, tg_key) if f.has(tg_key) else None
    if T_he is None:
        raise f.error(he_key, f"is missing; the simulated cell needs the true {he_key}")
    if T_tg is None:
        raise f.error(tg_key, f"is missing; the simulated cell needs the true {tg_key}")
    nf = f.sub("noise", required=False) or Fields({}, f.file, f"{f.path}.noise")
    jf = f.sub("target_jitter", required=False) or Fields({}, f.file, f"{f.path}.target_jitter")
    return SimulationConfig(
        seed=seed,
        cameras=tuple(cams),
        T_hand_eye=T_he,
        T_target=T_tg,
        rig=rig,
        robot_noise_m=nf.number("robot_mm", 0.05, minimum=0.0) / 1000.0,
        robot_noise_deg=nf.number("robot_deg", 0.005, minimum=0.0),
        target_jitter_mm=jf.number("mm", 0.0, minimum=0.0),
        target_jitter_deg=jf.number("deg", 0.0, minimum=0.0),
    )


def _cameras(
    f: Fields, driver: str, sim: SimulationConfig | None
) -> tuple[tuple[CameraSpec, ...], dict[str, dict[str, Any]]]:
    if driver == "simulated":
        assert sim is not None
        specs = tuple(CameraSpec(c.name, c.width, c.height) for c in sim.cameras)
        return specs, {c.name: {} for c in sim.cameras}
    lst = f.get("list")
    if not isinstance(lst, list) or not lst:
        raise f.error(
            "list",
            f"is missing; driver {driver!r} needs a list of {{name, width, height, ...}}}} cameras",
        )
    specs = []
    opts: dict[str, dict[str, Any]] = {}
    for i, c in enumerate(lst):
        cf = Fields(c, f.file, f"{f.path}.list[{i}]")
        name = cf.string("name")
        if name in opts:
            raise cf.error("name", f"{name!r} appears twice; camera names must be unique")
        specs.append(
            CameraSpec(name, cf.integer("width", minimum=1), cf.integer("height", minimum=1))
        )
        opts[name] = {k: v for k, v in cf.data.items() if k not in ("name", "width", "height")}
    return tuple(specs), opts


def truth_block(cfg: CellConfig) -> dict[str, Any]:
    """The session's ``simulation:`` block (result-file names) of a simulated cell."""
    from slidecal.routines.session import transform_to_dict

    sim = cfg.simulation
    if sim is None:
        return {}
    he_key, tg_key = _names(cfg.mount)
    frame = he_key.split("_")[1]  # tool | base
    ref = cfg.reference_camera
    out: dict[str, Any] = {
        "cameras": {c.name: {"K": c.K, "distortion": c.distortion} for c in sim.cameras},
    }
    if len(sim.cameras) == 1:
        out[he_key] = transform_to_dict(sim.T_hand_eye)
    else:
        for c in sim.cameras:
            T_ref_c = np.eye(4) if c.name == ref else np.linalg.inv(sim.rig[c.name])
            out[f"T_{frame}_{c.name}"] = transform_to_dict(sim.T_hand_eye @ T_ref_c)
        for name, T in sim.rig.items():
            out[f"T_{name}_{ref}"] = transform_to_dict(T)
    out[tg_key] = transform_to_dict(sim.T_target)
    out["noise"] = {
        "robot_mm": sim.robot_noise_m * 1000.0,
        "robot_deg": sim.robot_noise_deg,
        "cameras": {
            c.name: {
                "blur_sigma_px": c.blur_sigma_px,
                "noise_std": c.noise_std,
                "exposure": c.exposure,
            }
            for c in sim.cameras
        },
    }
    out["seed"] = sim.seed
    return out

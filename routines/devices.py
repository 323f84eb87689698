"""From a cell file to camera driver objects (:func:`camera_rig`, after :func:`check_libraries`),
and what the devices say about themselves into the session (:func:`record_devices`,
:func:`device_calibration_outputs`); the ``cameras:`` keys: docs/FORMATS.md.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from slidecal.routines.session import SESSION_FILE, Fields, load_yaml, write_atomic
from slidecal.solver.errors import InputError
from slidecal.solver.result import CalibrationResult

#: Driver -> (module it needs, the package that brings it, the slidecal extra).
LIBRARIES = {"ur": ("rtde_control", "ur-rtde", "ur"), "oak": ("depthai", "depthai", "oak")}
OAK_RIG_KEYS = ("driver", "reference", "list", "device_id", "fps", "resize", "exposure_us", "iso",
                "sync_tolerance_s")
OAK_CAMERA_KEYS = ("socket", "colour", "focus", "white_balance_k")
UVC_CAMERA_KEYS = ("source", "fourcc", "exposure", "focus", "fps", "drop_frames")
USER_FILE = "device_calibration_user.json"
FACTORY_FILE = "device_calibration_factory.json"


def _installed(module: str) -> bool:
    if module in sys.modules:  # imported already (or blocked: None)
        return sys.modules[module] is not None
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def check_libraries(cfg: Any) -> None:
    """``InputError`` when the cell names a driver whose library is not installed."""
    for section, driver in (("robot", cfg.robot.driver), ("cameras", cfg.camera_driver)):
        if driver in LIBRARIES:
            module, package, extra = LIBRARIES[driver]
            if not _installed(module):
                raise InputError(
                    f"is {driver!r}, which needs {package} (not installed); install it with "
                    f"pip install 'slidecal[{extra}]'",
                    where=f"{cfg.source}: {section}.driver",
                )


def camera_rig(cfg: Any) -> Any:
    """The camera driver object of a real cell (not opened)."""
    check_libraries(cfg)
    section = Fields(cfg.rig_options, cfg.source, "cameras")
    if cfg.camera_driver == "oak":
        return _oak(cfg, section)
    return _uvc(cfg, section)  # a real robot's cell names oak or uvc cameras (load_config)


def _camera_fields(cfg: Any, section: Fields) -> dict[str, Fields]:
    """Per camera its driver options (their keys checked by the cell's validation)."""
    return {
        c.name: Fields(cfg.camera_options[c.name], cfg.source, f"{section.path}.list[{i}]")
        for i, c in enumerate(cfg.cameras)
    }


def _oak(cfg: Any, section: Fields) -> Any:
    from slidecal.drivers.oak import DEFAULT_FPS, RESIZE_MODES, OakRig

    cams = _camera_fields(cfg, section)
    sockets = {n: f.string("socket") for n, f in cams.items()}
    colour = {n for n, f in cams.items() if f.boolean("colour", False)}
    focus = {n: f.integer("focus", minimum=0) for n, f in cams.items() if f.has("focus")}
    wb = {n: f.integer("white_balance_k", minimum=1000) for n, f in cams.items()
          if f.has("white_balance_k")}
    exposure = section.integer("exposure_us", minimum=1) if section.has("exposure_us") else None
    iso = section.integer("iso", minimum=100) if section.has("iso") else None
    device = cfg.device_id
    try:
        return OakRig(
            None if device is None else str(device),
            sockets,
            {c.name: (c.width, c.height) for c in cfg.cameras},
            colour=colour,
            exposure_us=exposure,
            iso=iso,
            focus=focus,
            white_balance_k=wb,
            fps=section.number("fps", DEFAULT_FPS, positive=True),
            resize_mode=section.choice("resize", RESIZE_MODES, "stretch"),
            sync_tolerance_s=section.optional_number("sync_tolerance_s", positive=True),
        )
    except InputError as e:
        if e.where:
            raise
        raise InputError(str(e), where=section.where()) from None


def _uvc(cfg: Any, section: Fields) -> Any:
    from slidecal.drivers.uvc import UvcCamera

    if len(cfg.cameras) != 1:
        raise section.error("list", f"holds {len(cfg.cameras)} cameras; a uvc cell has one")
    c = cfg.cameras[0]
    f = _camera_fields(cfg, section)[c.name]
    source = f.require("source")
    if isinstance(source, bool) or not isinstance(source, int | str):
        raise f.error("source", f"must be a device index or a path, got {source!r}")
    try:
        return UvcCamera(
            source,
            c.name,
            c.width,
            c.height,
            fourcc=str(f.get("fourcc")) if f.has("fourcc") else None,
            exposure=f.optional_number("exposure"),
            focus=f.optional_number("focus"),
            fps=f.optional_number("fps"),
            drop_frames=f.integer("drop_frames", 4, minimum=0),
        )
    except InputError as e:
        raise InputError(str(e), where=f.where()) from None


# ------------------------------------------------------------------------------ the session
def record_devices(rig: Any, session_dir: str | Path, working_distance_m: float) -> dict[str, Any]:
    """Write what the open rig reports into ``session_dir`` and return the session's ``devices:``
    block (``camera``, ``working_distance_m``, an OAK's ``calibration_files``); empty for rigs
    without a report."""
    capabilities = getattr(rig, "capabilities", None)
    if capabilities is None:
        return {}
    out = Path(session_dir)
    out.mkdir(parents=True, exist_ok=True)
    block: dict[str, Any] = {"camera": capabilities(), "working_distance_m": working_distance_m}
    calibrations = getattr(rig, "device_calibrations", None)
    if calibrations is not None:
        files = {}
        for kind, data in calibrations().items():
            if data is None:
                continue
            name = USER_FILE if kind == "user" else FACTORY_FILE
            write_atomic(out / name, json.dumps(data, indent=1))
            files[kind] = name
        block["calibration_files"] = files
    return {"devices": block}


def session_devices(session_dir: str | Path) -> dict[str, Any]:
    """The ``devices:`` block of a session (empty when it has none)."""
    data = load_yaml(Path(session_dir) / SESSION_FILE, "session file")
    block = data.get("devices") if isinstance(data, Mapping) else None
    return dict(block) if isinstance(block, Mapping) else {}


def oak_outputs(devices: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Camera name -> the OAK output record (socket, resize mode, focus ...), or empty."""
    camera = devices.get("camera") or {}
    return dict(camera.get("outputs") or {}) if camera.get("driver") == "oak" else {}


def read_device_calibration(session_dir: str | Path, devices: Mapping[str, Any], kind: str):
    """The depthai JSON dict of the device's ``user`` or ``factory`` calibration, or None."""
    name = (devices.get("calibration_files") or {}).get(kind)
    if name is None:
        return None
    path = Path(session_dir) / name
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the device calibration ({e})", where=str(path)) from None


def device_calibration_outputs(
    result: CalibrationResult, session_dir: str | Path, export_dir: str | Path
) -> tuple[list[Path], str]:
    """After a solve of an OAK session: the depthai export started from the device's own
    calibration, and summary lines comparing the device's calibrations with the result."""
    session_dir = Path(session_dir)
    if not any((session_dir / f).is_file() for f in (USER_FILE, FACTORY_FILE)):
        return [], ""  # not an OAK session, or a device without calibration: nothing to add
    devices = session_devices(session_dir)
    outputs = oak_outputs(devices)
    if not outputs or not set(result.cameras) <= set(outputs):
        return [], ""
    from slidecal.drivers import oak

    sockets = {n: o["socket"] for n, o in outputs.items()}
    lens = {n: o["focus"] for n, o in outputs.items() if o.get("focus") is not None}
    user = read_device_calibration(session_dir, devices, "user")
    streams = oak.stream_geometry(devices.get("camera") or {})
    Path(export_dir).mkdir(parents=True, exist_ok=True)
    paths, lines = [], []
    try:
        paths.append(
            oak.write_oak_calibration_json(
                result, Path(export_dir) / "depthai_calibration.json", sockets, base=user,
                lens_positions=lens, streams=streams,
            )
        )
    except InputError as e:
        lines.append(f"note: no depthai calibration export: {e}")
    distance = float(devices.get("working_distance_m") or 0.5)
    resize = next(iter(outputs.values())).get("resize_mode", "stretch")  # the rig's one mode
    for kind in ("factory", "user"):
        data = read_device_calibration(session_dir, devices, kind)
        if data is None:
            continue
        try:
            shift = oak.projection_shift_px(
                result, data, sockets, distance, resize, streams=streams
            )
        except InputError as e:
            lines.append(f"note: the device {kind} calibration was not compared: {e}")
            continue
        if shift:
            parts = ", ".join(
                f"{n} {v['rms_px']:.2f} rms / {v['max_px']:.2f} max" for n, v in shift.items()
            )
            lines.append(
                f"device {kind} calibration against this result, points at "
                f"{distance:.2f} m move (px): {parts}"
            )
    return paths, "".join(line + "\n" for line in lines)

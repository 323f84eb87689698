"""Write a session's calibration into its OAK device (``slidecal flash SESSION``): without
``--write`` only how far the device's calibration moves projected points against the result;
with it, the device's calibration saved as ``device_calibration_backup_<time>.json`` first, the
new one built from it, written into the user area (never the factory area) and read back.
To undo: flash the backup with depthai, or ``device.factoryResetCalibration()``.
"""

from __future__ import annotations

import argparse
import json
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.drivers import oak
from slidecal.routines.devices import oak_outputs, read_device_calibration, session_devices
from slidecal.routines.results_io import RESULT_FILE, read_result
from slidecal.routines.session import write_atomic
from slidecal.solver.errors import HardwareFault, InputError

help = "write a session's calibration into its OAK device's user area (with --write)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``slidecal flash`` arguments."""
    p.add_argument("session", help="session directory recorded with an OAK (holds session.yaml)")
    p.add_argument("--result", help="result file (default: SESSION_DIR/result.yaml)")
    p.add_argument("--device-id", help="the device to write (default: the session's device)")
    p.add_argument(
        "--write",
        action="store_true",
        help="really write the device's user calibration area (a backup is saved first)",
    )


def main(args: argparse.Namespace) -> int:
    """``slidecal flash``: print what was done; exit codes as every subcommand."""
    report = flash_session(args.session, args.result, args.device_id, write=args.write)
    print(report, end="")
    return 0


def _close(a: Any, b: Any, **tolerance: float) -> bool:
    x = np.asarray([] if a is None else a, float)
    y = np.asarray([] if b is None else b, float)
    return x.shape == y.shape and bool(np.allclose(x, y, **tolerance))


def _compare(a: dict[str, Any], b: dict[str, Any]) -> list[int]:
    """The camera sockets whose calibration differs between two depthai JSON dicts."""
    cams_a, cams_b = ({int(k): v for k, v in d.get("cameraData", [])} for d in (a, b))
    bad = sorted(set(cams_a) ^ set(cams_b))
    for key in set(cams_a) & set(cams_b):
        for field in ("intrinsicMatrix", "distortionCoeff", "width", "height"):
            if not _close(cams_a[key].get(field), cams_b[key].get(field), rtol=1e-6):
                bad.append(key)
        ea, eb = cams_a[key].get("extrinsics", {}), cams_b[key].get("extrinsics", {})
        ta, tb = ([e.get("translation", {}).get(k, 0.0) for k in "xyz"] for e in (ea, eb))
        if not (
            _close(ea.get("rotationMatrix"), eb.get("rotationMatrix"), atol=1e-7)
            and _close(ta, tb, atol=1e-6)
            and ea.get("toCameraSocket") == eb.get("toCameraSocket")
        ):
            bad.append(key)
    return sorted(set(bad))


def flash_session(
    session_dir: str | Path,
    result_path: str | Path | None = None,
    device_id: str | None = None,
    write: bool = False,
) -> str:
    """Flash (``write=True``) or describe the flash of a session's result; returns the report."""
    session_dir = Path(session_dir)
    devices = session_devices(session_dir)
    outputs = oak_outputs(devices)
    if not outputs:
        raise InputError(
            "was not recorded with an OAK (no devices.camera with driver oak); only OAK "
            "sessions can be flashed",
            where=str(session_dir / "session.yaml"),
        )
    result = read_result(Path(result_path) if result_path else session_dir / RESULT_FILE)
    missing = [n for n in result.cameras if n not in outputs]
    if missing:
        raise InputError(f"camera(s) {missing} of the result are not cameras of this session")
    sockets = {n: outputs[n]["socket"] for n in result.cameras}
    lens = {n: outputs[n]["focus"] for n in result.cameras if outputs[n].get("focus") is not None}
    recorded_id = (devices.get("camera") or {}).get("device_id")
    distance = float(devices.get("working_distance_m") or 0.5)
    resize = next(iter(outputs.values())).get("resize_mode", "stretch")
    streams = oak.stream_geometry(devices.get("camera") or {})
    lines = []
    recorded = read_device_calibration(session_dir, devices, "user")
    if recorded is not None:
        shift = oak.projection_shift_px(
            result, recorded, sockets, distance, resize, streams=streams
        )
        for name, v in shift.items():
            lines.append(
                f"{name} ({sockets[name]}): the device's calibration at recording time moves "
                f"points at {distance:.2f} m by {v['rms_px']:.2f} px rms, {v['max_px']:.2f} max"
            )
    if not write:
        lines.append(
            "nothing written; add --write to write this result into the device's user "
            "calibration area (its current calibration is saved to a backup file first)"
        )
        return "".join(line + "\n" for line in lines)

    target = device_id or recorded_id
    stamp = datetime.now().strftime("%Y%m%d_%H%M%S")
    with oak.OakCalibrationStore(target) as store:
        connected = store.connected_id()
        if recorded_id is not None and connected != recorded_id:
            raise InputError(
                f"the connected OAK is {connected}, not {recorded_id} that this session "
                "calibrated; connect that device (or pass --device-id to choose it)",
                where=str(session_dir),
            )
        current = store.read().eepromToJson()
        backup = session_dir / f"device_calibration_backup_{stamp}.json"
        write_atomic(backup, json.dumps(current, indent=1))
        handler = oak.oak_calibration_handler(
            result, sockets, base=current, lens_positions=lens, streams=streams
        )
        new = handler.eepromToJson()
        flashed = session_dir / f"device_calibration_flashed_{stamp}.json"
        write_atomic(flashed, json.dumps(new, indent=1))
        back = store.flash(handler).eepromToJson()
    differ = _compare(new, back)
    if differ:
        raise HardwareFault(
            f"the calibration read back from OAK {connected} differs from what was written "
            f"(sockets {differ}); flash it again, or restore the backup {backup}"
        )
    lines.append(f"backup of the device's calibration: {backup}")
    lines.append(
        f"written to the user calibration area of OAK {connected} and read back identical: "
        f"{flashed}"
    )
    return "".join(line + "\n" for line in lines)

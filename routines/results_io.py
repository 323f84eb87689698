"""Calibration results on disk: ``result.yaml`` (SESSION_FORMAT.md), exports, a human summary.

``result.yaml`` (format ``slidecal.result/1``) holds the contract's fields (``cameras`` with K,
distortion, std, reproj_rms_px; ``T_tool_cam`` / ``T_base_cam`` or ``T_tool_<name>`` per camera
of a rig; rig ``T_<name>_<ref>``) and these extensions, all additive:

- ``mount``, ``reference_camera``, ``converged``, ``iterations``;
- ``T_base_board`` (eye-in-hand) or ``T_tool_board`` (eye-to-hand): the estimated target pose;
- ``reprojection: {rms_px, sigma_px, per_image: [{frame, camera, rms_px}]}``; ``sigma_px`` is
  the noise estimated from the residuals (MATH.md Sec. 6);
- ``unobservable: {parameter: reason}``; ``messages: [...]`` (soft failures);
- ``scale_checks: [{frame_a, frame_b, robot_mm, camera_mm, ratio}]`` and ``scale_check:
  {median_ratio, worst_ratio, n}``;
- ``H_inf: {"a<-b": 3x3}``; ``outliers: [[frame, camera, corner id]]``;
  ``linear: {camera: K}`` (closed-form intrinsics before refinement);
- ``parameter_names`` and ``covariance`` (rows named by ``parameter_names``).

A value the data cannot determine is ``null``, never a number. ``T_tool_<name>`` of a rig's
non-reference camera is composed from the reference's hand-eye and the rig extrinsics; its std
is the root sum of squares of the two (correlations ignored: an approximation).

Exports for existing tools: OpenCV ``FileStorage`` YAML per camera (``camera_matrix``,
``distortion_coefficients``, ``image_width``, ``image_height``), ROS ``camera_info`` YAML per
camera, and the depthai calibration JSON through the OAK driver when the rig is an OAK.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.drivers.ur_pose import pendant_text
from slidecal.routines.session import (
    Fields,
    as_array,
    dump_yaml,
    load_yaml,
    plain,
    write_atomic,
)
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import rotation_angle_deg, rvec_from_R
from slidecal.solver.result import (
    CalibrationResult,
    CameraEstimate,
    ScaleCheck,
    TransformEstimate,
)

RESULT_FORMAT = "slidecal.result/1"
RESULT_FILE = "result.yaml"


# ----------------------------------------------------------------------------- names


def hand_eye_names(result: CalibrationResult) -> dict[str, str]:
    """Camera name -> the result file's name of its hand-eye transform.

    ``T_tool_cam`` / ``T_base_cam`` for a single camera; ``T_tool_<name>`` / ``T_base_<name>``
    for every camera of a rig. Empty without a robot.
    """
    frame = {"eye_in_hand": "tool", "eye_to_hand": "base"}.get(result.mount)
    if frame is None or result.hand_eye is None:
        return {}
    names = list(result.cameras)
    if len(names) == 1:
        return {names[0]: f"T_{frame}_cam"}
    return {n: f"T_{frame}_{n}" for n in names}


def target_pose_name(mount: str) -> str | None:
    """``T_base_board`` (eye-in-hand), ``T_tool_board`` (eye-to-hand), None otherwise."""
    return {"eye_in_hand": "T_base_board", "eye_to_hand": "T_tool_board"}.get(mount)


def _reference(result: CalibrationResult) -> str:
    return result.reference_camera or next(iter(result.cameras))


def hand_eye_transforms(result: CalibrationResult) -> dict[str, TransformEstimate]:
    """The hand-eye transform of every camera under its result-file name (see module doc)."""
    names = hand_eye_names(result)
    if not names:
        return {}
    he = result.hand_eye
    assert he is not None
    ref = _reference(result)
    out: dict[str, TransformEstimate] = {}
    for cam, key in names.items():
        if cam == ref:
            out[key] = TransformEstimate(key, he.R, he.t_m, he.std_rot_deg, he.std_t_mm)
            continue
        rig = result.rig.get(f"T_{cam}_{ref}")
        if rig is None or he.R is None or rig.R is None:
            out[key] = TransformEstimate(key, None, None)
            continue
        # T_tool_cam = T_tool_ref @ T_ref_cam = T_tool_ref @ inv(T_cam_ref)
        R_ref_cam = rig.R.T
        R = he.R @ R_ref_cam
        t = None
        if he.t_m is not None and rig.t_m is not None:
            t = he.R @ (-rig.R.T @ rig.t_m) + he.t_m
        out[key] = TransformEstimate(
            key,
            R,
            t,
            _rss(he.std_rot_deg, rig.std_rot_deg),
            _rss(he.std_t_mm, rig.std_t_mm) if t is not None else None,
        )
    return out


def _rss(a: float | None, b: float | None) -> float | None:
    if a is None or b is None:
        return None
    return float(np.hypot(a, b))


# ----------------------------------------------------------------------------- result.yaml


def _num(x: float | None) -> float | None:
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def transform_estimate_to_dict(t: TransformEstimate) -> dict[str, Any]:
    """``{R, t_m, std_rot_deg, std_t_mm}``; null where unobservable."""
    return {
        "R": plain(t.R) if t.R is not None else None,
        "t_m": plain(t.t_m) if t.t_m is not None else None,
        "std_rot_deg": _num(t.std_rot_deg),
        "std_t_mm": _num(t.std_t_mm) if t.t_m is not None else None,
    }


def camera_to_dict(c: CameraEstimate) -> dict[str, Any]:
    """One camera's block of ``result.yaml``."""
    return {
        "width": int(c.width),
        "height": int(c.height),
        "K": plain(np.asarray(c.K, dtype=float)),
        "distortion_model": "opencv5",
        "distortion": plain(np.asarray(c.distortion, dtype=float).reshape(-1)[:5]),
        "std": {k: _num(v) for k, v in c.std.items()},
        "reproj_rms_px": _num(c.reproj_rms_px),
    }


def result_to_dict(result: CalibrationResult) -> dict[str, Any]:
    """The ``result.yaml`` mapping of a result (see the module docstring)."""
    d: dict[str, Any] = {"format": RESULT_FORMAT}
    d["cameras"] = {n: camera_to_dict(c) for n, c in result.cameras.items()}
    for key, t in hand_eye_transforms(result).items():
        d[key] = transform_estimate_to_dict(t)
    for key, t in result.rig.items():
        d[key] = transform_estimate_to_dict(t)
    tname = target_pose_name(result.mount)
    if tname is not None and result.T_target is not None:
        d[tname] = transform_estimate_to_dict(result.T_target)
    d["mount"] = result.mount
    d["reference_camera"] = _reference(result)
    d["converged"] = bool(result.converged)
    d["iterations"] = int(result.iterations)
    d["reprojection"] = {
        "rms_px": _num(result.reproj_rms_px),
        "sigma_px": _num(result.sigma_px),
        "per_image": [
            {"frame": int(f), "camera": c, "rms_px": _num(v)}
            for (f, c), v in sorted(result.residuals_px.items())
        ],
    }
    d["unobservable"] = dict(result.unobservable)
    d["messages"] = list(result.messages)
    d["scale_checks"] = [
        {
            "frame_a": int(s.frame_a),
            "frame_b": int(s.frame_b),
            "robot_mm": _num(s.robot_mm),
            "camera_mm": _num(s.camera_mm),
            "ratio": _num(s.ratio),
        }
        for s in result.scale_checks
    ]
    d["scale_check"] = scale_check_summary(result.scale_checks)
    d["H_inf"] = {k: plain(v) for k, v in result.H_inf.items()}
    d["outliers"] = [[int(f), c, int(i)] for f, c, i in result.outliers]
    d["linear"] = {k: plain(v) for k, v in result.linear.items()}
    d["parameter_names"] = list(result.parameter_names)
    d["covariance"] = plain(result.covariance) if result.covariance is not None else None
    return d


def scale_check_summary(checks: tuple[ScaleCheck, ...]) -> dict[str, Any] | None:
    """Median and worst (farthest from 1) camera/robot length ratio; None without checks."""
    ratios = np.array([s.ratio for s in checks], dtype=float)
    ratios = ratios[np.isfinite(ratios)]
    if len(ratios) == 0:
        return None
    worst = ratios[int(np.argmax(np.abs(ratios - 1.0)))]
    return {"median_ratio": float(np.median(ratios)), "worst_ratio": float(worst), "n": len(ratios)}


def write_result(
    result: CalibrationResult, path: str | Path, header: Mapping[str, Any] | None = None
) -> Path:
    """Write ``result.yaml`` atomically; return its path. ``header``: written after
    ``format`` (slidecal version, time, cell file hash: :func:`slidecal.routines.exports.
    result_header`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    d = result_to_dict(result)
    if header:
        d = {"format": d.pop("format"), "header": dict(header), **d}
    write_atomic(path, dump_yaml(d))
    return path


def read_result(path: str | Path) -> CalibrationResult:
    """Read a ``result.yaml`` back into a :class:`CalibrationResult` (round trip of
    :func:`write_result`; the per-image residuals, outliers and covariance included)."""
    path = Path(path)
    data = load_yaml(path, "result file")
    f = Fields(data, path.name)
    fmt = f.require("format")
    if fmt != RESULT_FORMAT:
        raise f.error("format", f"is {fmt!r}; expected {RESULT_FORMAT!r}")
    cams: dict[str, CameraEstimate] = {}
    cf = f.sub("cameras")
    assert cf is not None
    for name in cf.data:
        c = cf.sub(str(name))
        assert c is not None
        cams[str(name)] = CameraEstimate(
            str(name),
            c.integer("width", minimum=1),
            c.integer("height", minimum=1),
            c.array("K", (3, 3)),
            c.array("distortion", (5,)),
            {k: (float(v) if v is not None else float("nan")) for k, v in c.get("std", {}).items()},
            float(c.get("reproj_rms_px", float("nan"))),
        )
    mount = f.string("mount", "eye_in_hand")
    ref = f.string("reference_camera", next(iter(cams)))

    def te(key: str, name: str | None = None) -> TransformEstimate | None:
        if not f.has(key):
            return None
        s = f.sub(key)
        assert s is not None
        return TransformEstimate(
            name or key,
            s.array("R", (3, 3)) if s.has("R") else None,
            s.array("t_m", (3,)) if s.has("t_m") else None,
            s.get("std_rot_deg"),
            s.get("std_t_mm"),
        )

    frame = {"eye_in_hand": "tool", "eye_to_hand": "base"}.get(mount)
    hand_eye = None
    if frame is not None:
        key = f"T_{frame}_cam" if len(cams) == 1 else f"T_{frame}_{ref}"
        hand_eye = te(key, f"T_{frame}_cam")
    rig = {f"T_{n}_{ref}": t for n in cams if n != ref if (t := te(f"T_{n}_{ref}")) is not None}
    tname = target_pose_name(mount)
    rep = f.sub("reprojection")
    assert rep is not None
    residuals = {
        (int(r["frame"]), str(r["camera"])): float(r["rms_px"])
        for r in rep.get("per_image", [])
        if r.get("rms_px") is not None
    }
    cov = f.get("covariance")
    return CalibrationResult(
        cameras=cams,
        hand_eye=hand_eye,
        rig=rig,
        T_target=te(tname) if tname else None,
        converged=f.boolean("converged", False),
        iterations=f.integer("iterations", 0),
        reproj_rms_px=float(rep.get("rms_px", float("nan"))),
        sigma_px=float(rep.get("sigma_px", float("nan"))),
        parameter_names=tuple(f.get("parameter_names", [])),
        covariance=as_array(cov, (-1, -1), f.where("covariance")) if cov is not None else None,
        residuals_px=residuals,
        outliers=tuple((int(a), str(b), int(c)) for a, b, c in f.get("outliers", [])),
        unobservable=dict(f.get("unobservable", {})),
        messages=tuple(f.get("messages", [])),
        scale_checks=tuple(
            ScaleCheck(int(s["frame_a"]), int(s["frame_b"]), s["robot_mm"], s["camera_mm"])
            for s in f.get("scale_checks", [])
        ),
        H_inf={k: np.asarray(v, dtype=float) for k, v in f.get("H_inf", {}).items()},
        linear={k: np.asarray(v, dtype=float) for k, v in f.get("linear", {}).items()},
        mount=mount,
        reference_camera=ref,
    )


# ----------------------------------------------------------------------------- exports


def write_opencv_yaml(camera: CameraEstimate, path: str | Path) -> Path:
    """OpenCV ``FileStorage`` YAML of one camera (as OpenCV's calibration sample writes it).

    Nodes: ``image_width``, ``image_height``, ``camera_name``, ``camera_matrix`` (3x3),
    ``distortion_coefficients`` (1x5: k1 k2 p1 p2 k3), ``avg_reprojection_error`` (px).
    """
    import cv2

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        fs.write("camera_name", camera.name)
        fs.write("camera_matrix", np.asarray(camera.K, dtype=np.float64))
        fs.write(
            "distortion_coefficients",
            np.asarray(camera.distortion, dtype=np.float64).reshape(1, -1)[:, :5],
        )
        fs.write("avg_reprojection_error", float(camera.reproj_rms_px))
    finally:
        fs.release()
    return path


def camera_info_dict(camera: CameraEstimate) -> dict[str, Any]:
    """The ROS ``camera_info`` YAML mapping (camera_calibration_parsers layout) of one camera.

    Monocular: rectification identity, projection ``[K | 0]``; ``plumb_bob`` is OpenCV's
    k1 k2 p1 p2 k3.
    """
    K = np.asarray(camera.K, dtype=float)
    P = np.hstack([K, np.zeros((3, 1))])
    return {
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "camera_name": camera.name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": plain(K.reshape(-1))},
        "distortion_model": "plumb_bob",
        "distortion_coefficients": {
            "rows": 1,
            "cols": 5,
            "data": plain(np.asarray(camera.distortion, dtype=float).reshape(-1)[:5]),
        },
        "rectification_matrix": {"rows": 3, "cols": 3, "data": plain(np.eye(3).reshape(-1))},
        "projection_matrix": {"rows": 3, "cols": 4, "data": plain(P.reshape(-1))},
    }


def write_camera_info(camera: CameraEstimate, path: str | Path) -> Path:
    """Write :func:`camera_info_dict` as YAML."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, dump_yaml(camera_info_dict(camera)))
    return path


def write_depthai_json(result: CalibrationResult, path: str | Path, sockets: Mapping[str, Any]):
    """The depthai calibration JSON of an OAK rig, written by the OAK driver's writer.

    ``sockets``: camera name -> board socket name (``CAM_A``...). Raises ``InputError`` when
    this slidecal has no OAK writer.
    """
    try:
        from slidecal.drivers import oak
    except ImportError:  # the OAK driver is optional at run time (depthai missing)
        oak = None
    writer = getattr(oak, "write_oak_calibration_json", None) if oak is not None else None
    if writer is None:
        raise InputError(
            "this slidecal has no depthai calibration writer (slidecal.drivers.oak."
            "write_oak_calibration_json); use the OpenCV or ROS exports"
        )
    return writer(result, Path(path), dict(sockets))


def write_exports(
    result: CalibrationResult,
    out_dir: str | Path,
    oak_sockets: Mapping[str, Any] | None = None,
) -> list[Path]:
    """OpenCV and ROS files per camera (``opencv_<name>.yaml``, ``camera_info_<name>.yaml``)
    and, for an OAK rig (``oak_sockets`` given), ``depthai_calibration.json``."""
    out = Path(out_dir)
    paths = []
    for name, cam in result.cameras.items():
        paths.append(write_opencv_yaml(cam, out / f"opencv_{name}.yaml"))
        paths.append(write_camera_info(cam, out / f"camera_info_{name}.yaml"))
    if oak_sockets:
        try:
            paths.append(write_depthai_json(result, out / "depthai_calibration.json", oak_sockets))
        except InputError:
            pass  # reported in the summary by the caller; the other exports stand
    return paths


# ----------------------------------------------------------------------------- summary


def _fmt(x: float | None, spec: str = ".3f") -> str:
    return "n/a" if x is None or not np.isfinite(x) else format(x, spec)


def summary_text(result: CalibrationResult, truth: Mapping[str, Any] | None = None) -> str:
    """A human summary: reprojection error, per-parameter std, hand-eye in mm and degrees,
    what was unobservable and why, the scale check, and (simulated runs) the errors against
    the truth."""
    lines = ["slidecal calibration result", "=" * 27]
    lines.append(
        f"converged: {'yes' if result.converged else 'NO'} after {result.iterations} iterations; "
        f"reprojection rms {_fmt(result.reproj_rms_px)} px, "
        f"noise estimate sigma {_fmt(result.sigma_px)} px"
    )
    for name, c in result.cameras.items():
        K = np.asarray(c.K)
        std = c.std
        lines.append(
            f"camera {name} ({c.width}x{c.height}), reprojection rms {_fmt(c.reproj_rms_px)} px"
        )
        for label, val in (
            ("fx", K[0, 0]),
            ("fy", K[1, 1]),
            ("cx", K[0, 2]),
            ("cy", K[1, 2]),
            ("s", K[0, 1]),
        ):
            lines.append(f"  {label:3s} = {val:10.3f} px  +- {_fmt(std.get(label))} px")
        dist = np.asarray(c.distortion).reshape(-1)
        for label, val in zip(("k1", "k2", "p1", "p2", "k3"), dist[:5], strict=False):
            lines.append(f"  {label:3s} = {val:+.6f}     +- {_fmt(std.get(label), '.6f')}")
    for key, t in hand_eye_transforms(result).items():
        lines.extend(_transform_lines(key, t))
    for key, t in result.rig.items():
        lines.extend(_transform_lines(key, t))
    tname = target_pose_name(result.mount)
    if tname and result.T_target is not None:
        lines.extend(_transform_lines(tname, result.T_target))
    if result.unobservable:
        lines.append("not determined by this data (fixed, not estimated):")
        lines.extend(f"  {k}: {v}" for k, v in result.unobservable.items())
    sc = scale_check_summary(result.scale_checks)
    if sc is not None:
        ok = abs(sc["worst_ratio"] - 1.0) < 0.01
        lines.append(
            f"scale check ({sc['n']} moves, camera/robot length): median "
            f"{sc['median_ratio']:.4f}, worst {sc['worst_ratio']:.4f}"
            + ("" if ok else "  <- check the board's square size and the robot's TCP/scale")
        )
    if result.outliers:
        lines.append(f"outliers flagged and down-weighted: {len(result.outliers)} corners")
    for m in result.messages:
        lines.append(f"note: {m}")
    if truth:
        errs = errors_against_truth(result, truth)
        if errs:
            lines.append("errors against the simulated truth:")
            lines.extend(f"  {k} = {_fmt(v, '.4g')}" for k, v in errs.items())
    return "\n".join(lines) + "\n"


def _transform_lines(key: str, t: TransformEstimate) -> list[str]:
    if t.R is None:
        return [f"{key}: rotation not determined"]
    rv = np.degrees(rvec_from_R(t.R))
    out = [
        f"{key}: rotation {np.linalg.norm(rv):.3f} deg about axis "
        f"{_unit(rv)} (+- {_fmt(t.std_rot_deg, '.4f')} deg)"
    ]
    if t.t_m is None:
        out.append("  translation: not determined (needs rotations about two axes)")
    else:
        x, y, z = np.asarray(t.t_m) * 1000.0
        out.append(f"  translation {x:.2f} {y:.2f} {z:.2f} mm (+- {_fmt(t.std_t_mm, '.3f')} mm)")
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = t.R, t.t_m
        out.append(f"  as the pendant shows it: {pendant_text(T)}")
    return out


def _unit(v: np.ndarray) -> str:
    n = np.linalg.norm(v)
    u = v / n if n > 0 else v
    return "[" + ", ".join(f"{x:+.3f}" for x in u) + "]"


# ----------------------------------------------------------------------------- truth


def errors_against_truth(result: CalibrationResult, truth: Mapping[str, Any]) -> dict[str, float]:
    """Errors of a result against a session's ``simulation:`` block (same names).

    Keys: ``<cam>.fx_rel`` (relative), ``<cam>.fx_px``, ``fy``, ``cx``, ``cy`` (pixels);
    ``<T_name>.rot_deg`` (angle of R_est R_true'), ``<T_name>.t_mm`` (translation error norm)
    for every hand-eye, rig and target transform present in both.
    """
    out: dict[str, float] = {}
    tcams = truth.get("cameras") or {}
    for name, c in result.cameras.items():
        if name not in tcams:
            continue
        Kt = np.asarray(tcams[name]["K"], dtype=float)
        K = np.asarray(c.K, dtype=float)
        out[f"{name}.fx_rel"] = float(abs(K[0, 0] - Kt[0, 0]) / Kt[0, 0])
        for label, (i, j) in (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2))):
            out[f"{name}.{label}_px"] = float(abs(K[i, j] - Kt[i, j]))
    est: dict[str, TransformEstimate] = dict(hand_eye_transforms(result))
    est.update(result.rig)
    tname = target_pose_name(result.mount)
    if tname and result.T_target is not None:
        est[tname] = result.T_target
    for key, t in est.items():
        tt = truth.get(key)
        if not isinstance(tt, Mapping) or t.R is None or "R" not in tt:
            continue
        out[f"{key}.rot_deg"] = rotation_angle_deg(t.R, np.asarray(tt["R"], dtype=float))
        if t.t_m is not None and tt.get("t_m") is not None:
            dt = np.asarray(t.t_m) - np.asarray(tt["t_m"], dtype=float)
            out[f"{key}.t_mm"] = float(np.linalg.norm(dt) * 1000.0)
    return out


def truth_transform(truth: Mapping[str, Any], key: str) -> np.ndarray | None:
    """A 4x4 transform from the ``simulation:`` block, or None."""
    tt = truth.get(key)
    if not isinstance(tt, Mapping) or tt.get("R") is None or tt.get("t_m") is None:
        return None
    T = np.eye(4)
    T[:3, :3] = np.asarray(tt["R"], dtype=float)
    T[:3, 3] = np.asarray(tt["t_m"], dtype=float)
    return T

"""Calibration results on disk: ``result.yaml`` (``slidecal.result/1``, docs/FORMATS.md: its
fields, the covariance's parameter names, older results still read), the OpenCV and ROS
exports, a human summary. A value the data cannot determine is ``null``, never a number."""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import astuple, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.drivers.ur_pose import T_from_ur_pose, pendant_text
from slidecal.routines.schema import (
    Fields,
    load_yaml,
    plain,
    unknown_key_error,
    write_yaml,
)
from slidecal.solver.camera import DISTORTION_MODELS, distortion_model
from slidecal.solver.geometry import T_from_Rt, rotation_angle_deg, rvec_from_R
from slidecal.solver.numeric import median
from slidecal.solver.problem import hand_eye_names, mount_names
from slidecal.solver.result import (
    BoardShape,
    CalibrationResult,
    CameraEstimate,
    ModelAdequacy,
    RobotAccuracy,
    ScaleCheck,
    TransformEstimate,
)
from slidecal.solver.robot_error import effective_truth
from slidecal.solver.uncertainty import is_legacy, legacy_layout, propagate, reported_names

RESULT_FORMAT = "slidecal.result/1"
RESULT_FILE = "result.yaml"


# ----------------------------------------------------------------------------- names


def _reference(result: CalibrationResult) -> str:
    return result.reference_camera or next(iter(result.cameras))


def hand_eye_transforms(result: CalibrationResult) -> dict[str, TransformEstimate]:
    """The hand-eye transform of every camera under its result-file name (see module doc)."""
    he = result.hand_eye
    if he is None:
        return {}
    names = hand_eye_names(result.mount, list(result.cameras))
    ref = _reference(result)
    named = result.named_covariance
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
            named.std_rot_deg(key) if named is not None else None,
            named.std_t_mm(key) if named is not None and t is not None else None,
        )
    return out


def transforms(result: CalibrationResult) -> dict[str, TransformEstimate]:
    """Every transform of a result under its result-file name, in the file's order: the
    hand-eyes, the rig's ``T_<name>_<ref>``, the target pose."""
    out = {**hand_eye_transforms(result), **result.rig}
    frames = mount_names(result.mount)
    if frames is not None and result.T_target is not None:
        out[frames.target] = result.T_target
    return out


def _named_from_legacy(
    pnames: list[str],
    cov: np.ndarray | None,
    cams: dict[str, CameraEstimate],
    ref: str,
    mount: str,
    hand_eye: TransformEstimate | None,
    target: TransformEstimate | None,
    rig: dict[str, TransformEstimate],
) -> tuple[list[str], np.ndarray | None]:
    """A covariance written with the optimiser's names (``X0.r0``, ``Y.t1``, ``cam.f``: results
    of earlier versions) converted to the reported quantities; other names pass unchanged."""
    if not is_legacy(pnames):
        return pnames, cov

    def T(t: TransformEstimate | None) -> np.ndarray | None:
        if t is None or t.R is None:
            return None
        return T_from_Rt(t.R, np.zeros(3) if t.t_m is None else t.t_m)

    T_cam_ref = {c: T(t) for c in cams if c != ref and (t := rig.get(f"T_{c}_{ref}")) is not None}
    layout = legacy_layout(
        tuple(pnames),
        tuple(cams),
        ref,
        mount,
        T(hand_eye),
        T(target),
        {c: v for c, v in T_cam_ref.items() if v is not None},
    )
    if cov is None:
        return list(reported_names(layout, tuple(pnames))), None
    named = propagate(layout, tuple(pnames), cov)
    return list(named.names), named.matrix


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
        "distortion_model": distortion_model(c.distortion),
        "distortion": plain(np.asarray(c.distortion, dtype=float).reshape(-1)),
        "std": {k: _num(v) for k, v in c.std.items()},
        "reproj_rms_px": _num(c.reproj_rms_px),
    }


def result_to_dict(result: CalibrationResult) -> dict[str, Any]:
    """The ``result.yaml`` mapping of a result (docs/FORMATS.md)."""
    d: dict[str, Any] = {"format": RESULT_FORMAT}
    d["cameras"] = {n: camera_to_dict(c) for n, c in result.cameras.items()}
    for key, t in transforms(result).items():
        d[key] = transform_estimate_to_dict(t)
    d["mount"] = result.mount
    d["reference_camera"] = _reference(result)
    d["converged"] = bool(result.converged)
    d["iterations"] = int(result.iterations)
    d["reprojection"] = {
        "rms_px": _num(result.reproj_rms_px),
        "sigma_px": _num(result.sigma_px),
        "per_image": _rows(
            [(f, c, v) for (f, c), v in sorted(result.residuals_px.items())],
            "reprojection.per_image[]",
        ),
    }
    d["unobservable"] = dict(result.unobservable)
    d["messages"] = list(result.messages)
    d["scale_checks"] = _rows(
        [(*astuple(s), s.ratio) for s in result.scale_checks], "scale_checks[]"
    )
    d["scale_check"] = scale_check_summary(result.scale_checks)
    d["H_inf"] = {k: plain(v) for k, v in result.H_inf.items()}
    d["outliers"] = [[int(f), c, int(i)] for f, c, i in result.outliers]
    d["linear"] = {k: plain(v) for k, v in result.linear.items()}
    d["parameter_names"] = list(result.parameter_names)
    d["covariance"] = plain(result.covariance) if result.covariance is not None else None
    ad = result.adequacy
    if ad is not None:
        d["adequacy"] = {
            "adequate": bool(ad.adequate),
            "reasons": list(ad.reasons),
            "detector_noise_px": {k: _num(v) for k, v in ad.detector_noise_px.items()},
            "normalised_rms": {k: _num(v) for k, v in ad.normalised_rms.items()},
            "worst_frames": _rows(ad.worst_frames, "adequacy.worst_frames[]"),
        }
    bd = result.board
    if bd is not None:
        d["board"] = {
            "bow_mm": [_num(v) for v in bd.bow_mm],
            "bow_std_mm": [_num(v) for v in bd.bow_std_mm],
            "flatness_mm": _num(bd.flatness_mm),
            "print_tolerance": _num(bd.print_tolerance),
        }
    ra = result.robot_accuracy
    if ra is not None:
        d["robot_accuracy"] = {
            "translation_mm": _num(ra.translation_mm),
            "rotation_deg": _num(ra.rotation_deg),
            "estimated": bool(ra.estimated),
            "worst_frames": _rows(ra.worst_frames, "robot_accuracy.worst_frames[]"),
        }
        if ra.left_out:
            d["robot_accuracy"]["left_out_frames"] = _rows(
                ra.left_out, "robot_accuracy.left_out_frames[]"
            )
    return d


#: The scale check is inconclusive (and fails) when its tolerance exceeds this many times its
#: floor: the moves disagree with each other about the scale.
SCALE_INCONCLUSIVE = 5.0


def scale_tolerance(ratios: np.ndarray, floor: float) -> tuple[float, float]:
    """(median ratio, tolerance) of the moves' camera/robot length ratios: the tolerance is the
    larger of ``floor`` and four standard errors of the median (1.4826 MAD / sqrt(n) * 1.25)."""
    m = median(ratios)
    mad = median(np.abs(ratios - m)) * 1.4826
    se = 1.25 * mad / np.sqrt(len(ratios))
    return m, max(floor, 4.0 * se)


def scale_check_summary(checks: tuple[ScaleCheck, ...]) -> dict[str, Any] | None:
    """Median and worst (farthest from 1) camera/robot length ratio; None without checks."""
    ratios = np.array([s.ratio for s in checks], dtype=float)
    ratios = ratios[np.isfinite(ratios)]
    if len(ratios) == 0:
        return None
    worst = ratios[int(np.argmax(np.abs(ratios - 1.0)))]
    return {"median_ratio": median(ratios), "worst_ratio": float(worst), "n": len(ratios)}


def write_result(
    result: CalibrationResult, path: str | Path, header: Mapping[str, Any] | None = None
) -> Path:
    """Write ``result.yaml`` atomically; return its path. ``header``: written after
    ``format`` (slidecal version, time, cell file hash: :func:`slidecal.routines.exports.
    result_header`)."""
    d = result_to_dict(result)
    if header:
        d = {"format": d.pop("format"), "header": dict(header), **d}
    return write_yaml(path, d)


#: The keys of ``result.yaml`` besides the transforms (named ``T_<a>_<b>``): one list, kept in
#: step with :func:`result_to_dict`; the reader refuses any other key.
RESULT_KEYS = (
    "format",
    "cameras",
    "mount",
    "reference_camera",
    "converged",
    "iterations",
    "reprojection",
    "unobservable",
    "messages",
    "scale_checks",
    "scale_check",
    "H_inf",
    "outliers",
    "linear",
    "parameter_names",
    "covariance",
    "adequacy",
    "robot_accuracy",
    "board",
    "header",
)
#: The keys of the parts of ``result.yaml``.
RESULT_PART_KEYS: dict[str, tuple[str, ...]] = {
    "cameras.*": ("width", "height", "K", "distortion_model", "distortion", "std", "reproj_rms_px"),
    "transform": ("R", "t_m", "std_rot_deg", "std_t_mm"),
    "reprojection": ("rms_px", "sigma_px", "per_image"),
    "reprojection.per_image[]": ("frame", "camera", "rms_px"),
    "scale_checks[]": ("frame_a", "frame_b", "robot_mm", "camera_mm", "ratio"),
    "scale_check": ("median_ratio", "worst_ratio", "n"),
    "adequacy": ("adequate", "reasons", "detector_noise_px", "normalised_rms", "worst_frames"),
    "adequacy.worst_frames[]": ("frame", "camera", "normalised_rms"),
    "robot_accuracy": (
        "translation_mm",
        "rotation_deg",
        "estimated",
        "worst_frames",
        "left_out_frames",
    ),
    "board": ("bow_mm", "bow_std_mm", "flatness_mm", "print_tolerance"),
    "robot_accuracy.worst_frames[]": ("frame", "translation_mm", "rotation_deg"),
    "robot_accuracy.left_out_frames[]": ("frame", "translation_mm", "rotation_deg"),
    "header": ("slidecal_version", "created_utc", "cell", "cell_sha256", "verdict"),
}
RESULT_MOUNTS = ("eye_in_hand", "eye_to_hand", "none")
_TRANSFORM_KEY = re.compile(r"T_[A-Za-z0-9]+_[A-Za-z0-9_]+")


def read_result(path: str | Path) -> CalibrationResult:
    """Read a ``result.yaml`` back into a :class:`CalibrationResult` (the inverse of
    :func:`write_result`: per-image residuals, outliers and covariance included). Every field is
    checked; a problem is one ``InputError`` naming ``result.yaml: field``."""
    path = Path(path)
    return result_from_dict(load_yaml(path, "result file"), path.name)


def _nullable(f: Fields, key: str, minimum: float | None = None) -> float:
    """A number or null (NaN in the result object)."""
    return f.number(key, minimum=minimum) if f.has(key) else float("nan")


def _numbers(f: Fields, key: str, names: list[str] | None = None) -> dict[str, float]:
    sub = f.section(key, names)
    return {str(k): _nullable(sub, str(k), minimum=0.0) for k in sub.data}


def _rows(rows: Sequence[Sequence[Any]], part: str) -> list[dict[str, Any]]:
    """The entries of a list of ``result.yaml``: each row's values under the keys of ``part``
    (frame ids as integers, camera names as text, numbers null where not finite)."""
    return [
        {
            k: v if isinstance(v, str) else int(v) if k.startswith("frame") else _num(v)
            for k, v in zip(RESULT_PART_KEYS[part], row, strict=True)
        }
        for row in rows
    ]


def _rows_from(
    f: Fields, key: str, hint: str, names: list[str], keys: Sequence[str] | None = None
) -> tuple[tuple[Any, ...], ...]:
    """The list ``key`` of ``f`` read back (:func:`_rows`): per entry the values of ``keys``
    (default: all of the part's keys) in order, frame ids non-negative, cameras of ``names``."""
    part = f"{f.path}.{key}[]" if f.path else f"{key}[]"
    rows = []
    for wf in f.entries(key, RESULT_PART_KEYS[part], required=False, hint=hint):
        rows.append(
            tuple(
                wf.integer(k, minimum=0)
                if k.startswith("frame")
                else wf.choice(k, names)
                if k == "camera"
                else _nullable(wf, k, minimum=0.0)
                for k in keys or RESULT_PART_KEYS[part]
            )
        )
    return tuple(rows)


def _adequacy_from(f: Fields, names: list[str]) -> ModelAdequacy:
    a = f.section("adequacy", RESULT_PART_KEYS["adequacy"])
    worst = _rows_from(a, "worst_frames", "{frame, camera, ...}", names)
    return ModelAdequacy(
        _numbers(a, "detector_noise_px", names),
        _numbers(a, "normalised_rms", names),
        worst,  # type: ignore[arg-type]
        a.boolean("adequate"),
        tuple(a.strings("reasons")),
    )


def _board_from(f: Fields) -> BoardShape:
    b = f.section("board", RESULT_PART_KEYS["board"])
    bow, sd = b.array("bow_mm", (2,)), b.array("bow_std_mm", (2,))
    return BoardShape(
        (float(bow[0]), float(bow[1])),
        (float(sd[0]), float(sd[1])),
        b.number("flatness_mm", minimum=0.0),
        b.number("print_tolerance", minimum=0.0),
    )


def _robot_accuracy_from(f: Fields) -> RobotAccuracy:
    r = f.section("robot_accuracy", RESULT_PART_KEYS["robot_accuracy"])
    lists = {k: _rows_from(r, k, "{frame, ...}", []) for k in ("worst_frames", "left_out_frames")}
    return RobotAccuracy(
        _nullable(r, "translation_mm", minimum=0.0),
        _nullable(r, "rotation_deg", minimum=0.0),
        lists["worst_frames"],
        r.boolean("estimated"),
        lists["left_out_frames"],
    )


def _cameras_from(f: Fields) -> dict[str, CameraEstimate]:
    """The ``cameras:`` section of a result, by name."""
    cams: dict[str, CameraEstimate] = {}
    cf = f.sub("cameras")
    assert cf is not None
    if not cf.data:
        raise cf.error(None, "is empty; a result holds at least one camera")
    for name in cf.cameras():
        c = cf.section(name, RESULT_PART_KEYS["cameras.*"])
        model = c.choice("distortion_model", tuple(DISTORTION_MODELS), "opencv5")
        dist = c.distortion("distortion")
        if distortion_model(dist) != model:
            raise c.error(
                "distortion_model",
                f"is {model}, but distortion has {len(dist)} values, the "
                f"{distortion_model(dist)} model's; make them agree",
            )
        cams[name] = CameraEstimate(
            name,
            c.integer("width", minimum=1, maximum=100_000),
            c.integer("height", minimum=1, maximum=100_000),
            c.array("K", (3, 3)),
            dist,
            _numbers(c, "std"),
            _nullable(c, "reproj_rms_px", minimum=0.0),
        )
    return cams


def result_from_dict(data: Any, source: str = RESULT_FILE) -> CalibrationResult:
    """Validate a parsed ``result.yaml`` (see :func:`read_result`)."""
    f = Fields(data, source)
    fmt = f.require("format")
    if fmt != RESULT_FORMAT:
        raise f.error("format", f"is {fmt!r}; expected {RESULT_FORMAT!r}")
    for key in f.data:
        if key not in RESULT_KEYS and not (isinstance(key, str) and _TRANSFORM_KEY.fullmatch(key)):
            raise unknown_key_error(f.where(str(key)), key, RESULT_KEYS)
    cams = _cameras_from(f)
    names = list(cams)
    mount = f.choice("mount", RESULT_MOUNTS, "eye_in_hand")
    ref = f.camera("reference_camera", names)

    def te(key: str) -> TransformEstimate | None:
        if not f.has(key):
            return None
        s = f.section(key, RESULT_PART_KEYS["transform"])
        R = s.rotation("R") if s.has("R") else None
        t = s.array("t_m", (3,)) if s.has("t_m") else None
        return TransformEstimate(
            key,
            R,
            t,
            s.optional_number("std_rot_deg", minimum=0.0),
            s.optional_number("std_t_mm", minimum=0.0),
        )

    # every transform named is read (and must be one this result can hold)
    Ts = {k: te(k) for k in f.data if isinstance(k, str) and _TRANSFORM_KEY.fullmatch(k)}
    frames = mount_names(mount)
    he = Ts.get(hand_eye_names(mount, names)[ref]) if frames is not None else None
    hand_eye = None if he is None or frames is None else replace(he, name=frames.hand_eye)
    rig = {k: t for n in cams if n != ref if (t := Ts.get(k := f"T_{n}_{ref}")) is not None}
    rep = f.section("reprojection", RESULT_PART_KEYS["reprojection"])
    per_image = _rows_from(rep, "per_image", "{frame, camera, rms_px}", names)
    residuals = {(fid, cam): rms for fid, cam, rms in per_image if np.isfinite(rms)}
    pnames = f.strings("parameter_names")
    cov = None
    if f.has("covariance"):
        cov = f.array("covariance", (len(pnames), len(pnames)))
        if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-12 * max(1.0, np.abs(cov).max())):
            raise f.error("covariance", "is not symmetric; it was not written by slidecal")
    outliers = []
    for i, o in enumerate(f.list("outliers", required=False, hint="[frame, camera, corner id]")):
        ok = isinstance(o, list) and len(o) == 3 and isinstance(o[1], str) and o[1] in cams
        if not (ok and all(isinstance(v, int) and not isinstance(v, bool) for v in o[::2])):
            raise f.error(f"outliers[{i}]", "must be [frame id, camera name, corner id]")
        outliers.append((int(o[0]), str(o[1]), int(o[2])))
    unobs = f.section("unobservable")
    for k, v in unobs.data.items():
        if not isinstance(v, str):
            raise unobs.error(str(k), "must be the reason as text")
    scale_keys = [fl.name for fl in fields(ScaleCheck)]  # not the ratio, which they give
    checks = [ScaleCheck(*r) for r in _rows_from(f, "scale_checks", "scale check", [], scale_keys)]
    sc_sum = f.section("scale_check", RESULT_PART_KEYS["scale_check"])
    for k in ("median_ratio", "worst_ratio"):
        _nullable(sc_sum, k)
    if sc_sum.has("n"):
        sc_sum.integer("n", minimum=0)
    hf = f.section("H_inf")
    H_inf = {}
    for k in hf.data:
        parts = str(k).split("<-")
        if len(parts) != 2 or parts[0] not in cams or parts[1] not in cams:
            raise hf.error(str(k), "must be named 'a<-b' with two of the result's cameras")
        H_inf[str(k)] = hf.array(str(k), (3, 3))
    lf = f.section("linear")
    linear = {k: lf.array(k, (3, 3)) for k in lf.cameras(names)}
    hf_ = f.section("header", RESULT_PART_KEYS["header"])  # provenance: checked, not kept
    for k in hf_.data:
        if hf_.get(k) is not None and not isinstance(hf_.get(k), str):
            raise hf_.error(str(k), "must be text (as slidecal writes it)")
    adequacy = _adequacy_from(f, names) if f.has("adequacy") else None
    robot_accuracy = _robot_accuracy_from(f) if f.has("robot_accuracy") else None
    board = _board_from(f) if f.has("board") else None
    T_target = Ts.get(frames.target) if frames is not None else None
    pnames, cov = _named_from_legacy(pnames, cov, cams, ref, mount, hand_eye, T_target, rig)
    return CalibrationResult(
        cameras=cams,
        hand_eye=hand_eye,
        rig=rig,
        T_target=T_target,
        converged=f.boolean("converged", False),
        iterations=f.integer("iterations", 0, minimum=0),
        reproj_rms_px=_nullable(rep, "rms_px", minimum=0.0),
        sigma_px=_nullable(rep, "sigma_px", minimum=0.0),
        parameter_names=tuple(pnames),
        covariance=cov,
        residuals_px=residuals,
        outliers=tuple(outliers),
        unobservable={str(k): v for k, v in unobs.data.items()},
        messages=tuple(f.strings("messages")),
        scale_checks=tuple(checks),
        H_inf=H_inf,
        linear=linear,
        mount=mount,
        reference_camera=ref,
        adequacy=adequacy,
        robot_accuracy=robot_accuracy,
        board=board,
    )


# ----------------------------------------------------------------------------- summary

#: The intrinsics a summary lists: name and place in K
K_ENTRIES = (("fx", (0, 0)), ("fy", (1, 1)), ("cx", (0, 2)), ("cy", (1, 2)), ("s", (0, 1)))


def _fmt(x: float | None, spec: str = ".3f") -> str:
    """A figure of the summary; "n/a" when absent, powers of ten when it is a million or more
    (a one-sigma of a result the data does not determine, which the verdict rejects)."""
    if x is None or not np.isfinite(x):
        return "n/a"
    return format(x, ".1e") if abs(x) >= 1e6 else format(x, spec)


def summary_text(
    result: CalibrationResult,
    truth: Mapping[str, Any] | None = None,
    scale_floor: float = 0.01,
) -> str:
    """A human summary: reprojection, per-parameter std, hand-eye in mm and degrees, what was
    unobservable and why, the scale check against ``scale_floor`` (the verdict's
    ``scale_tolerance``) and, for simulated runs, the errors against the truth."""
    lines = ["slidecal calibration result", "=" * 27]
    lines.append(
        f"converged: {'yes' if result.converged else 'NO'} after {result.iterations} iterations; "
        f"reprojection rms {_fmt(result.reproj_rms_px)} px (the solve's: robot poses "
        f"corrected within the arm's learned accuracy), noise estimate sigma "
        f"{_fmt(result.sigma_px)} px"
    )
    lines.extend(_adequacy_lines(result))
    for name, c in result.cameras.items():
        K = np.asarray(c.K)
        std = c.std
        lines.append(
            f"camera {name} ({c.width}x{c.height}), reprojection rms {_fmt(c.reproj_rms_px)} px"
        )
        dist = np.asarray(c.distortion).reshape(-1)
        names = DISTORTION_MODELS[distortion_model(dist)]
        rows = [(label, K[ij], "10.3f", ".3f", " px") for label, ij in K_ENTRIES]
        rows += [(lb, v, "+.6f", ".6f", "") for lb, v in zip(names, dist, strict=True)]
        for label, val, spec, std_spec, unit in rows:
            value = f"  {label:3s} = {val:{spec}}{unit:5s}"
            if label in std or not std:  # no std at all: the covariance was not computed
                lines.append(f"{value}+- {_fmt(std.get(label), std_spec)}{unit}")
            else:  # held by the options (the skew: 0 unless estimated), not estimated
                lines.append(f"{value}(fixed)")
    for key, t in transforms(result).items():
        lines.extend(_transform_lines(key, t))
    if result.unobservable:
        lines.append("not determined by this data (fixed, not estimated):")
        lines.extend(f"  {k}: {v}" for k, v in result.unobservable.items())
    sc = scale_check_summary(result.scale_checks)
    if sc is not None:
        ratios = np.array([c.ratio for c in result.scale_checks], dtype=float)
        median, tol = scale_tolerance(ratios[np.isfinite(ratios)], scale_floor)
        if tol > SCALE_INCONCLUSIVE * scale_floor:
            verdict = "  <- the moves disagree too much to check the scale"
        elif abs(median - 1.0) > tol:
            verdict = "  <- check target.square_size_m and the robot's TCP and units"
        else:
            verdict = ""
        lines.append(
            f"scale check ({sc['n']} moves, camera/robot length): median "
            f"{sc['median_ratio']:.4f} (allowed 1 +- {tol:.4f}), worst move "
            f"{sc['worst_ratio']:.4f}" + verdict
        )
    if result.outliers:
        lines.append(f"outliers flagged and down-weighted: {len(result.outliers)} corners")
    for m in result.messages:
        lines.append(f"note: {m}")
    if truth:
        errs = errors_against_truth(result, truth)
        if errs:
            lines.append(f"errors against the simulated truth ({truth_kind(truth)}):")
            lines.extend(f"  {k} = {_fmt(v, '.4g')}" for k, v in errs.items())
    return "\n".join(lines) + "\n"


def _adequacy_lines(result: CalibrationResult) -> list[str]:
    """The model-adequacy verdict and the robot's accuracy as the camera saw it."""
    out = []
    ad = result.adequacy
    if ad is not None:
        noise = ", ".join(
            f"{c} {_fmt(v)} px (residuals {_fmt(ad.normalised_rms.get(c), '.2f')}x)"
            for c, v in ad.detector_noise_px.items()
        )
        if ad.adequate:
            out.append(f"model adequacy: the model explains the images; detector noise {noise}")
        else:
            out.append("MODEL INADEQUATE: do not use this result")
            out.extend(f"  - {r}" for r in ad.reasons)
            out.append(f"  detector noise {noise}")
    ra = result.robot_accuracy
    if ra is not None:
        how = "estimated from the images" if ra.estimated else "from the options"
        if ra.estimated and ra.translation_mm == 0.0 and ra.rotation_deg == 0.0:
            out.append("robot accuracy: the measured poses explain the images (taken as exact)")
        else:
            worst = ", ".join(f"{f} ({t:.2f} mm, {r:.3f} deg)" for f, t, r in ra.worst_frames[:3])
            out.append(
                f"robot accuracy ({how}): {ra.translation_mm:.3f} mm, {ra.rotation_deg:.4f} deg "
                f"rms per axis" + (f"; worst frames {worst}" if worst else "")
            )
    bd = result.board
    if bd is not None:
        out.append(
            f"board: bow {bd.bow_mm[0]:+.3f} mm along x, {bd.bow_mm[1]:+.3f} mm along y "
            f"(+- {bd.bow_std_mm[0]:.3f}, {bd.bow_std_mm[1]:.3f}); tolerance assumed: flatness "
            f"{bd.flatness_mm:.2f} mm, print {100.0 * bd.print_tolerance:.3g} % "
            "(target.flatness_mm, target.print_tolerance)"
        )
    return out


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
        out.append(f"  as the pendant shows it: {pendant_text(T_from_Rt(t.R, t.t_m))}")
    return out


def _unit(v: np.ndarray) -> str:
    n = np.linalg.norm(v)
    u = v / n if n > 0 else v
    return "[" + ", ".join(f"{x:+.3f}" for x in u) + "]"


# ----------------------------------------------------------------------------- truth


def errors_against_truth(result: CalibrationResult, truth: Mapping[str, Any]) -> dict[str, float]:
    """Errors of a result against a session's ``simulation:`` block (same names): ``<cam>.fx_rel``,
    ``<cam>.fx_px`` .. ``cy`` (pixels), ``<T_name>.rot_deg`` and ``.t_mm`` per transform in both.
    The hand-eye and the target pose are judged against :func:`judged_truth`."""
    out: dict[str, float] = {}
    tcams = truth.get("cameras") or {}
    for name, c in result.cameras.items():
        if name not in tcams:
            continue
        Kt = np.asarray(tcams[name]["K"], dtype=float)
        K = np.asarray(c.K, dtype=float)
        out[f"{name}.fx_rel"] = float(abs(K[0, 0] - Kt[0, 0]) / Kt[0, 0])
        for label, ij in K_ENTRIES[:4]:
            out[f"{name}.{label}_px"] = float(abs(K[ij] - Kt[ij]))
    judged = judged_truth(result, truth)
    for key, t in transforms(result).items():
        T_true = judged.get(key)
        if T_true is None or t.R is None:
            continue
        out[f"{key}.rot_deg"] = rotation_angle_deg(t.R, T_true[:3, :3])
        if t.t_m is not None:
            dt = np.asarray(t.t_m) - T_true[:3, 3]
            out[f"{key}.t_mm"] = float(np.linalg.norm(dt) * 1000.0)
    return out


def judged_truth(result: CalibrationResult, truth: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """The transforms (4x4, result-file names) a result is judged against: the block's, hand-eyes
    and target pose replaced, where the block records the arm's true and reported poses, by the
    effective truth (``robot_error.effective_truth``) over the frames the solve used."""
    out = {
        k: T
        for k in truth
        if isinstance(k, str) and re.fullmatch(r"T_\w+_\w+", k)
        for T in [truth_transform(truth, k)]
        if T is not None
    }
    frames = truth_frames(truth)
    used = {fid for fid, _ in result.residuals_px}
    frames = [f for f in frames if not used or f[0] in used]
    he_names = {} if result.hand_eye is None else hand_eye_names(result.mount, list(result.cameras))
    tname = getattr(mount_names(result.mount), "target", None)
    ref_key = he_names.get(_reference(result))
    if not frames or ref_key not in out or tname not in out:
        return out
    rot_deg, mm = _robot_sigma(result, truth)
    T_he, T_tg = out[ref_key], out[tname]
    T_he_eff, T_tg_eff = effective_truth(
        result.mount, [f[1] for f in frames], [f[2] for f in frames], T_he, T_tg, rot_deg, mm
    )
    shift = T_he_eff @ np.linalg.inv(T_he)  # the same for every camera of a rig
    for key in he_names.values():
        if key in out:
            out[key] = shift @ out[key]
    out[ref_key], out[tname] = T_he_eff, T_tg_eff
    return out


def truth_frames(truth: Mapping[str, Any]) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """``(frame id, true T_base_tool, measured T_base_tool)`` of the block's ``frames``."""
    out = []
    for fr in truth.get("frames") or []:
        out.append(
            (
                int(fr["id"]),
                T_from_ur_pose(np.asarray(fr["T_base_tool"], dtype=float)),
                T_from_ur_pose(np.asarray(fr["T_base_tool_measured"], dtype=float)),
            )
        )
    return out


def truth_kind(truth: Mapping[str, Any] | None) -> str:
    """Which truth :func:`errors_against_truth` judges the hand-eye and target against."""
    if truth and truth.get("frames"):
        n = len(truth["frames"])
        return (
            f"hand-eye and target: the effective truth over {n} frames, the physical one moved "
            "by the arm's constant error; intrinsics and rig: the physical truth"
        )
    return "the physical truth"


def _robot_sigma(result: CalibrationResult, truth: Mapping[str, Any]) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) weights of the effective truth: the accuracy the
    solve estimated, else the simulated arm's (kinematic error, else measurement noise)."""
    ra = result.robot_accuracy
    if ra is not None and (ra.rotation_deg > 0 or ra.translation_mm > 0):
        return max(ra.rotation_deg, 1e-4), max(ra.translation_mm, 1e-3)
    noise = truth.get("noise") or {}
    ke = noise.get("kinematic_error") or {}
    rot = float(ke.get("deg", noise.get("robot_deg", 0.0)) or 0.0)
    mm = float(ke.get("mm", noise.get("robot_mm", 0.0)) or 0.0)
    return max(rot, 1e-4), max(mm, 1e-3)


def truth_transform(truth: Mapping[str, Any], key: str) -> np.ndarray | None:
    """A 4x4 transform from the ``simulation:`` block, or None."""
    tt = truth.get(key)
    if not isinstance(tt, Mapping) or tt.get("R") is None or tt.get("t_m") is None:
        return None
    return T_from_Rt(np.asarray(tt["R"], dtype=float), np.asarray(tt["t_m"], dtype=float))

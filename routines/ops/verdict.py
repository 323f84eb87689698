"""The verdict a nightly job can trust (``verdict.yaml``): ``accepted | rejected | drifted |
ok``, with reasons. The gate (:func:`judge`) tests the solve against the cell's ``limits:``
(:class:`Limits`); its tests, the file and the exit codes: docs/UNATTENDED.md."""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slidecal.routines.ops.install import installed_session
from slidecal.routines.results_io import (
    SCALE_INCONCLUSIVE,
    _num,
    hand_eye_transforms,
    scale_tolerance,
)
from slidecal.routines.session import Fields, dump_yaml, write_atomic
from slidecal.solver import drift
from slidecal.solver.adequacy import LEFT_OUT, RECORDS_WRONG
from slidecal.solver.camera import (
    DISTORTION_MODELS,
    distortion_model,
    opencv_view,
    project,
    project_with_jacobians,
    undistort_normalised,
)
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import rotation_angle_deg
from slidecal.solver.numeric import median
from slidecal.solver.problem import CalibrationProblem, hand_eye_names
from slidecal.solver.result import CalibrationResult

VERDICT_FORMAT = "slidecal.verdict/1"
VERDICT_FILE = "verdict.yaml"

#: The exit code of each verdict (docs/UNATTENDED.md)
EXIT_CODES = {"accepted": 0, "ok": 0, "rejected": 4, "drifted": 5}


@dataclass(frozen=True)
class Limits:
    """The gate's limits (the cell file's ``limits:`` section; every field optional): their
    meaning and defaults are the table of docs/UNATTENDED.md."""

    max_rms_px: float = 1.0
    fx_rel_std: float = 0.005
    cxy_std_px: float = 3.0
    hand_eye_rot_std_deg: float = 0.2
    hand_eye_t_std_mm: float = 3.0
    hand_eye_rot_std_deg_from_translations: float = 1.0
    cxy_std_px_from_translations: float = 8.0
    fx_rel_std_from_translations: float = 0.01
    scale_tolerance: float = 0.01
    min_coverage: float = 0.25
    coverage_grid: tuple[int, int] = (8, 6)
    max_change_sigma: float = 4.0
    max_change_px: float = 0.6
    working_distance_m: float = 0.5
    change_region: float = 0.5
    check_max_rms_ratio: float = 1.6
    check_max_px: float = 0.5
    check_change_px: float = 0.8
    focal_change_stat: float = 12.0
    focal_change_rel: float = 0.001
    max_robot_error_mm: float = 2.0
    max_robot_error_deg: float = 0.2
    max_robot_error_ratio: float = 2.5
    max_projection_std_px: float = 10.0
    max_projection_std_px_from_translations: float = 15.0


def limits_from_dict(data: Any, source: str = "cell.yaml", path: str = "limits") -> Limits:
    """:class:`Limits` from a cell file's ``limits:`` mapping (unknown keys refused)."""
    if data is None:
        return Limits()
    f = Fields(data, source, path)
    base = Limits()
    known = [x.name for x in fields(Limits)]
    for k in f.data:
        if k not in known:
            near = difflib.get_close_matches(str(k), known, n=1)
            hint = f"did you mean {near[0]!r}? " if near else ""
            raise f.error(str(k), f"is not a limit; {hint}the limits are {known}")
    kw: dict[str, Any] = {}
    for x in fields(Limits):
        if x.name == "coverage_grid":
            if f.has(x.name):
                g = f.get(x.name)
                if not (
                    isinstance(g, list)
                    and len(g) == 2
                    and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in g)
                ):
                    raise f.error(x.name, "must be [columns, rows], two positive integers")
                kw[x.name] = (int(g[0]), int(g[1]))
            continue
        kw[x.name] = f.number(x.name, getattr(base, x.name), positive=True)
    return Limits(**kw)


@dataclass(frozen=True)
class Check:
    """One test of the gate: its name, whether it passed, the figure, the limit, one line."""

    test: str
    passed: bool
    value: float | None
    limit: float | None
    message: str


def _check(
    test: str, ok: Any, value: float | None, limit: float | None, message: str, fix: str = ""
) -> Check:
    """A :class:`Check` whose message, when it failed, ends with ``fix`` (the cause, the cure)."""
    return Check(test, bool(ok), value, limit, message + ("" if ok else fix))


@dataclass(frozen=True)
class Verdict:
    """What the gate decided and why. ``installed``: the comparison with the installed
    calibration (None when there was none)."""

    verdict: str
    command: str
    checks: tuple[Check, ...]
    installed: dict[str, Any] | None = None
    notes: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def reasons(self) -> tuple[Check, ...]:
        """The failed tests."""
        return tuple(c for c in self.checks if not c.passed)

    @property
    def exit_code(self) -> int:
        """0 accepted / ok, 4 rejected, 5 drifted."""
        return EXIT_CODES[self.verdict]

    def lines(self) -> list[str]:
        """Human lines: the verdict, then each reason (or note)."""
        out = [f"verdict: {self.verdict}"]
        out += [f"  reason: {c.message}" for c in self.reasons]
        out += [f"  note: {n}" for n in self.notes]
        return out


def write_verdict(v: Verdict, directory: str | Path) -> Path:
    """Write ``verdict.yaml`` (the verdict, its reasons, every check, the comparison with the
    installed calibration, the notes) atomically into ``directory``; return its path."""

    def c(ch: Check) -> dict[str, Any]:
        d = asdict(ch)
        d["value"], d["limit"] = _num(ch.value), _num(ch.limit)
        return d

    d: dict[str, Any] = {
        "format": VERDICT_FORMAT,
        "verdict": v.verdict,
        "command": v.command,
        "exit_code": v.exit_code,
        "reasons": [{k: x for k, x in c(ch).items() if k != "passed"} for ch in v.reasons],
        "checks": [c(ch) for ch in v.checks],
    }
    if v.installed is not None:
        d["installed"] = v.installed
    if v.notes:
        d["notes"] = list(v.notes)
    d.update(v.extra)
    path = Path(directory) / VERDICT_FILE
    write_atomic(path, dump_yaml(d))
    return path


# ----------------------------------------------------------------------------- the gate


def judge(
    result: CalibrationResult,
    limits: Limits | None = None,
    problem: CalibrationProblem | None = None,
    installed: CalibrationResult | None = None,
    command: str = "run",
    session_status: str = "complete",
    installed_path: str | None = None,
    installed_problem: CalibrationProblem | None = None,
    sockets: Mapping[str, str] | None = None,
) -> Verdict:
    """The verdict of a solved calibration (docs/UNATTENDED.md). ``installed_problem``:
    the installed session's frames (default: the ``session.yaml`` an install store keeps
    beside ``installed_path``), for the paired comparison at the poses both sessions share.
    ``sockets``: camera name -> OAK board socket, as the session recorded them."""
    lim = limits or Limits()
    checks: list[Check] = []
    notes: list[str] = []
    if session_status != "complete":
        checks.append(
            Check(
                "session",
                False,
                None,
                None,
                f"the session is {session_status} (the run stopped before its plan was done); "
                "run it again or resume it with slidecal run --resume",
            )
        )
    checks.append(
        Check(
            "converged",
            bool(result.converged),
            float(result.iterations),
            None,
            f"the solver {'converged' if result.converged else 'did NOT converge'} "
            f"after {result.iterations} iterations",
        )
    )
    checks.extend(_reprojection(result, lim))
    ad = result.adequacy
    if ad is not None and not ad.adequate and any(RECORDS_WRONG in r for r in ad.reasons):
        # the robot's records are wrong: every other figure comes from a solve on them
        return Verdict("rejected", command, tuple(c for c in checks if c.test != "converged"))
    checks.extend(_stds(result, lim))
    checks.extend(_scale(result, lim))
    projection, beyond = _projection(result, lim, problem)
    checks.extend(projection)
    notes.extend(beyond)
    checks.extend(_stereo_order(result, sockets or {}))
    if problem is not None:
        checks.extend(_coverage(problem, lim))
        checks.extend(_intrinsics_change(problem, result, lim))
    checks.extend(_arm(result, lim))
    cmp_info = None
    quality_ok = all(c.passed for c in checks)
    if installed is not None:
        checks.extend(_arm(result, lim, installed))
        change, cmp_info = compare(result, installed, lim)
        if installed_path is not None:
            cmp_info = {"path": installed_path, **cmp_info}
        checks.extend(change)
        if problem is not None:
            if installed_problem is None and installed_path is not None:
                try:  # None when the install keeps no session (or is a result file)
                    installed_problem = installed_session(installed_path)
                except InputError as e:
                    notes.append(
                        f"the installed session could not be read ({e}); no paired comparison"
                    )
            if installed_problem is not None:
                paired, info = paired_compare(
                    problem, installed_problem, installed, lim.max_change_px, lim.change_region
                )
                checks.extend(paired)
                cmp_info["paired"] = info
                if not info["usable"]:
                    notes.append(f"no paired comparison: {info['why']}")
    if any(c.test == "std" and not c.passed and c.limit is not None for c in checks):
        notes.append(STD_HINT)  # not for a transform the data did not determine at all
    for name, why in result.unobservable.items():
        notes.append(f"{name} not determined: {why}")
    if one_orientation(result) and result.cameras:
        notes.append(ONE_ORIENTATION_FOCAL)
    notes.extend(m for m in result.messages if LEFT_OUT in m)  # frames left out for their poses
    if not quality_ok:
        verdict = "rejected"
    elif installed is not None and not all(c.passed for c in checks):
        verdict = "drifted"
    else:
        verdict = "accepted"
    return Verdict(verdict, command, tuple(checks), cmp_info, tuple(notes))


def _reprojection(result: CalibrationResult, lim: Limits) -> list[Check]:
    ad = result.adequacy
    if ad is not None:
        worst = max(ad.normalised_rms.values(), default=float("nan"))
        msg = (
            f"model adequacy: reprojection rms {worst:.2f} times the detector's noise"
            if ad.adequate
            else "model adequacy failed: " + "; ".join(ad.reasons)
        )
        return [Check("adequacy", bool(ad.adequate), _num(worst), None, msg)]
    out = []
    for name, c in result.cameras.items():  # a result holds a camera at least
        r = c.reproj_rms_px
        ok = bool(np.isfinite(r) and r <= lim.max_rms_px)
        out.append(
            Check(
                "reprojection",
                ok,
                _num(r),
                lim.max_rms_px,
                f"camera {name}: reprojection rms {r:.3f} px (limit {lim.max_rms_px:g} px"
                + ("" if ok else "; the model or the robot poses do not explain the images")
                + ")",
            )
        )
    return out


#: A session of one orientation: its focal lengths rest on what it cannot check
#: (docs/ERROR_MODEL.md Sec. 6); said, not rejected, since its principal point and hand-eye
#: rotation stand
ONE_ORIENTATION_FOCAL = (
    "the focal lengths of a session of one orientation rest on the lengths of the arm's moves "
    "along the viewing direction and on a detector unbiased with the pattern's size, which "
    "one orientation cannot check (real arms gave them 0.5-2.8 % low): before using fx, fy as "
    "the camera's calibration, add two tilted orientations (plan: tilts_deg) or give the "
    "intrinsics from a calibration that had them"
)

#: What a user can do about a one-sigma beyond its limit (a note of the verdict): the data
#: tell no more; more of them, or a limit that fits the cell
STD_HINT = (
    "a one-sigma beyond its limit is what this session's data can tell: more frames or tilts "
    "narrow it (slidecal run extends its plan for this by itself), or set the limit named in "
    "the cell file's limits: section (slidecal solve judges with the limits the session "
    "recorded; --config CELL overrides them)"
)


def _std_check(
    what: str, value: float | None, limit: float, unit: str, fmt: str, note: str, scale: float = 1
) -> Check:
    """The ``std`` check of one one-sigma ``value`` (None: not determined) against ``limit``."""
    shown = "unknown" if value is None else f"{value * scale:{fmt}} {unit}"
    ok = value is not None and value <= limit
    return Check("std", ok, value, limit, f"{what} one-sigma {shown} ({note})")


def one_orientation(result: CalibrationResult) -> bool:
    """A robot session of one orientation: its hand-eye rotation determined, its translation
    not (the intrinsics rest on the moves alone; the ``_from_translations`` limits apply)."""
    he = result.hand_eye
    return he is not None and he.R is not None and he.t_m is None


def _stds(result: CalibrationResult, lim: Limits) -> list[Check]:
    out = []
    alone = one_orientation(result)  # the hand-eye from translations alone
    cxy_lim = lim.cxy_std_px_from_translations if alone else lim.cxy_std_px
    fx_lim = lim.fx_rel_std_from_translations if alone else lim.fx_rel_std
    suffix = "_from_translations" if alone else ""  # the limits' field names
    for name, c in result.cameras.items():
        K = np.asarray(c.K, dtype=float)
        for p, val in (("fx", K[0, 0]), ("fy", K[1, 1])):
            s = _num(c.std.get(p))
            rel = s / abs(val) if s is not None and val != 0 else None
            note = f"limit {fx_lim * 100:g} %; limits.fx_rel_std{suffix}"
            out.append(_std_check(f"camera {name}: {p}", rel, fx_lim, "%", ".3f", note, 100))
        for p in ("cx", "cy"):
            one = ", a session of one orientation" if alone else ""
            note = f"limit {cxy_lim:g} px{one}; limits.cxy_std_px{suffix}"
            s = _num(c.std.get(p))
            out.append(_std_check(f"camera {name}: {p}", s, cxy_lim, "px", ".3f", note))
    transforms = [result.hand_eye] if result.hand_eye is not None else []
    transforms.extend(result.rig.values())
    for t in transforms:
        if t.R is None:
            out.append(Check("std", False, None, None, f"{t.name}: rotation not determined"))
            continue
        full = t.t_m is not None  # else: from translations alone (no rotation in the session)
        rot_lim = lim.hand_eye_rot_std_deg if full else lim.hand_eye_rot_std_deg_from_translations
        note = (
            f"limit {rot_lim:g} deg" + ("" if full else ", a hand-eye from translations alone")
            + f"; limits.hand_eye_rot_std_deg{'' if full else '_from_translations'}"
        )
        s = _num(t.std_rot_deg)
        out.append(_std_check(f"{t.name}: rotation", s, rot_lim, "deg", ".4f", note))
        if t.t_m is not None:
            t_lim = lim.hand_eye_t_std_mm
            note = f"limit {t_lim:g} mm; limits.hand_eye_t_std_mm"
            s = _num(t.std_t_mm)
            out.append(_std_check(f"{t.name}: translation", s, t_lim, "mm", ".3f", note))
    return out


#: What a learned arm error beyond its limit may be instead of the arm (the solve takes any
#: error that moves whole frames as the arm's)
NOT_THE_ARM = (
    "the solve took as the arm's error what is something else: a focus or lens that moved, a "
    "board that moved or is not the size described, a camera loose on its mount"
)


def _arm(
    result: CalibrationResult, lim: Limits, installed: CalibrationResult | None = None
) -> list[Check]:
    """The ``arm`` check: the arm's learned accuracy against its class's level, or (with
    ``installed``) against a multiple of the installed calibration's."""
    ra = result.robot_accuracy
    if ra is None or not ra.estimated:
        return []
    t, r = ra.translation_mm, ra.rotation_deg
    if installed is None:
        ok = t <= lim.max_robot_error_mm and r <= lim.max_robot_error_deg
        return [
            _check(
                "arm",
                ok,
                t,
                lim.max_robot_error_mm,
                f"the arm's accuracy learned from the session: {t:.2f} mm, {r:.3f} deg rms per "
                f"axis (limits.max_robot_error_mm {lim.max_robot_error_mm:g}, "
                f"limits.max_robot_error_deg {lim.max_robot_error_deg:g}: a six-axis arm's)",
                f"; beyond any arm of its class: {NOT_THE_ARM}",
            )
        ]
    old = installed.robot_accuracy
    if old is None or not old.estimated or old.translation_mm <= 0:
        return []
    ratio = t / old.translation_mm
    ok = ratio <= lim.max_robot_error_ratio
    return [
        _check(
            "arm",
            ok,
            ratio,
            lim.max_robot_error_ratio,
            f"the arm's accuracy learned from the session, {t:.2f} mm rms per axis, is "
            f"{ratio:.1f} times the installed calibration's ({old.translation_mm:.2f} mm; "
            f"limits.max_robot_error_ratio {lim.max_robot_error_ratio:g})",
            f": the same arm does not err more; {NOT_THE_ARM}",
        )
    ]


def _scale(result: CalibrationResult, lim: Limits) -> list[Check]:
    ratios = np.array([s.ratio for s in result.scale_checks], dtype=float)
    ratios = ratios[np.isfinite(ratios)]
    if len(ratios) == 0:
        return []
    m, tol = scale_tolerance(ratios, lim.scale_tolerance)
    if tol > SCALE_INCONCLUSIVE * lim.scale_tolerance:
        return [
            Check(
                "scale",
                False,
                tol,
                SCALE_INCONCLUSIVE * lim.scale_tolerance,
                f"the camera/robot length ratios of the {len(ratios)} moves scatter too much to "
                f"check the scale (median {m:.4f} +- {tol:.4f}); check target.square_size_m, "
                "the robot's TCP and units",
            )
        ]
    ok = abs(m - 1.0) <= tol
    return [
        _check(
            "scale",
            ok,
            abs(m - 1.0),
            tol,
            f"camera/robot length ratio {m:.4f} over {len(ratios)} moves (allowed 1 +- {tol:.4f})",
            "; check target.square_size_m and the robot's TCP and units",
        )
    ]


#: A stereo head's sockets (depthai's): CAM_B is the left camera and CAM_C the right one, seen
#: from behind the head as its images are, so the right camera lies along the left one's +x
STEREO_SOCKETS = ("CAM_B", "CAM_C")


def _stereo_order(result: CalibrationResult, sockets: Mapping[str, str]) -> list[Check]:
    """The ``stereo`` check: the camera on the right socket must lie along the left one's +x
    (swapped images or sockets put it on the -x side at the same baseline)."""
    by_socket = {str(s): n for n, s in sockets.items()}
    left, right = (by_socket.get(s) for s in STEREO_SOCKETS)
    if left not in result.cameras or right not in result.cameras:
        return []
    ref = result.reference_camera or next(iter(result.cameras))
    T = {ref: np.eye(4)}  # T_<camera>_<reference>
    T.update({k[2:].removesuffix(f"_{ref}"): t.T for k, t in result.rig.items() if t.T is not None})
    if left not in T or right not in T:
        return []
    x_mm = float((T[left] @ np.linalg.inv(T[right]))[0, 3] * 1000.0)  # right's origin, left's x
    ok = x_mm > 0
    return [
        _check(
            "stereo",
            ok,
            x_mm,
            0.0,
            f"camera {right} ({STEREO_SOCKETS[1]}) lies {x_mm:+.1f} mm along the x axis of camera "
            f"{left} ({STEREO_SOCKETS[0]})",
            ", where a stereo head's right camera lies along the left one's +x: the "
            "two cameras' images are swapped (or their sockets); give each camera its "
            "socket in the cell file's cameras: section and record again",
        )
    ]


def coverage_fraction(
    problem: CalibrationProblem, camera: str, grid: tuple[int, int] = (8, 6)
) -> tuple[float, np.ndarray]:
    """Fraction of a ``grid`` ([columns, rows]) of image cells holding a detected corner of
    ``camera`` in any frame, and the (rows, columns) count of corners per cell."""
    spec = next(c for c in problem.cameras if c.name == camera)
    nx, ny = grid
    counts = np.zeros((ny, nx), dtype=int)
    for fr in problem.frames:
        det = fr.detections.get(camera)
        if det is None or len(det.ids) == 0:
            continue
        px = np.asarray(det.px, dtype=float)
        ix = np.clip((px[:, 0] / spec.width * nx).astype(int), 0, nx - 1)
        iy = np.clip((px[:, 1] / spec.height * ny).astype(int), 0, ny - 1)
        np.add.at(counts, (iy, ix), 1)
    return float(np.mean(counts > 0)), counts


def uncertainty_map(result: CalibrationResult, camera: str, n: tuple[int, int] = (32, 20)):
    """One-sigma pixel error (``n[1]`` x ``n[0]`` grid over the image) of the projection of a
    fixed ray through each grid pixel, from the covariance of the camera's intrinsics; None
    without a covariance."""
    if result.covariance is None:
        return None
    cam = result.cameras[camera]
    lens = DISTORTION_MODELS[distortion_model(cam.distortion)]
    names = [f"{camera}.{p}" for p in ("fx", "fy", "cx", "cy", "s", *lens)]
    idx = [
        (k, result.parameter_names.index(nm))
        for k, nm in enumerate(names)
        if nm in result.parameter_names
    ]
    if not idx:
        return None
    C = np.asarray(result.covariance, float)[np.ix_([i for _, i in idx], [i for _, i in idx])]
    K, d = np.asarray(cam.K, float), np.asarray(cam.distortion, float).reshape(-1)
    u, v = np.meshgrid(np.linspace(0, cam.width - 1, n[0]), np.linspace(0, cam.height - 1, n[1]))
    px = np.stack([u.ravel(), v.ravel()], 1)
    rays = undistort_normalised(K, d, px)
    at = project_with_jacobians(K, d, np.hstack([rays, np.ones((len(rays), 1))]))
    J = np.concatenate([at.d_K, at.d_dist], axis=2)[:, :, [k for k, _ in idx]]  # (fx .. s, lens)
    var = np.einsum("nij,jk,nik->n", J, C, J)
    return np.sqrt(np.maximum(var, 0.0)).reshape(n[1], n[0])


def _projection(
    result: CalibrationResult, lim: Limits, problem: CalibrationProblem | None
) -> tuple[list[Check], list[str]]:
    """The ``projection`` check per camera (docs/UNATTENDED.md; the whole image without the
    problem), and a note where the rest of the image is beyond the limit."""
    out, notes = [], []
    alone = one_orientation(result)
    limit = lim.max_projection_std_px_from_translations if alone else lim.max_projection_std_px
    field_name = f"limits.max_projection_std_px{'_from_translations' if alone else ''}"
    for name in result.cameras:
        m = uncertainty_map(result, name, (16, 10))
        if m is None:
            continue
        seen = np.ones(m.shape, bool)
        if problem is not None and name in {c.name for c in problem.cameras}:
            counts = coverage_fraction(problem, name, (16, 10))[1]
            if counts.any():  # the cells the views reached, and their neighbours
                seen = cv2.dilate((counts > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        inside, worst = float(np.max(m[seen])), float(np.max(m))
        ok = inside <= limit
        out.append(
            _check(
                "projection",
                ok,
                inside,
                limit,
                f"camera {name}: a point's projection one-sigma up to {inside:.2f} px where its "
                f"views reached, {worst:.2f} px over the whole image (limit {limit:g} px, "
                f"{field_name})",
                "; the intrinsics are not known",
            )
        )
        if ok and worst > limit:
            notes.append(
                f"camera {name}: beyond the image area its views covered, the projection "
                f"one-sigma reaches {worst:.1f} px (limit {limit:g} px, {field_name}): the "
                "calibration holds where the board was seen; views that bring the board to the "
                "image's corners and edges extend it"
            )
    return out, notes


def _coverage(problem: CalibrationProblem, lim: Limits) -> list[Check]:
    out = []
    for c in problem.cameras:
        frac, _ = coverage_fraction(problem, c.name, lim.coverage_grid)
        ok = frac >= lim.min_coverage
        nx, ny = lim.coverage_grid
        out.append(
            _check(
                "coverage",
                ok,
                frac,
                lim.min_coverage,
                f"camera {c.name}: corners seen in {frac * 100:.0f} % of the {nx}x{ny} image "
                f"cells (at least {lim.min_coverage * 100:.0f} %)",
                "; plan views that bring the target to the image's edges",
            )
        )
    return out


#: Fewest corners of an image for its free pose to tell a focal scale
INTRINSICS_MIN_CORNERS = 8


def focal_change(
    problem: CalibrationProblem, camera: str, K0: np.ndarray, dist0: np.ndarray
) -> tuple[float, float, int] | None:
    """The likeliest change of ``camera``'s focal length between two parts of the session, from
    the images alone at ``K0``, ``dist0`` (the ``intrinsics`` test of docs/UNATTENDED.md):
    ``(statistic, relative change, frame index where it starts)``; None with fewer than four
    images."""
    rows = []  # per image: frame index, N (3, 3), g (3,), rss, corners
    for k, f in enumerate(problem.frames):
        d = f.detections.get(camera)
        if d is None or len(d.ids) < INTRINSICS_MIN_CORNERS:
            continue
        obj = problem.target.points_m[d.ids].astype(float)
        K, dist, px = opencv_view(K0, dist0, np.asarray(d.px, float))  # a fisheye: undistorted
        ok, rv, tv = cv2.solvePnP(obj, px, K, dist)
        if not ok:
            continue
        proj, jac = cv2.projectPoints(obj, rv, tv, K, dist)
        r = (px - proj.reshape(-1, 2)).reshape(-1)
        J = np.column_stack([K[0, 0] * jac[:, 6] + K[1, 1] * jac[:, 7], jac[:, 8], jac[:, 9]])
        Q = np.linalg.qr(jac[:, :6])[0]  # the pose's directions, taken out
        J, r = J - Q @ (Q.T @ J), r - Q @ (Q.T @ r)
        rows.append((k, J.T @ J, J.T @ r, float(r @ r), len(px)))
    if len(rows) < 4:
        return None

    sum_N = np.cumsum([r[1] for r in rows], axis=0)  # each part's sums from the running ones
    sum_g = np.cumsum([r[2] for r in rows], axis=0)

    def explained(split: int) -> tuple[float, float]:
        """Misfit explained by a focal scale per part (one when ``split`` is 0) and a common
        principal point correction, and the second part's scale against the first's."""
        parts = [(sum_N[-1], sum_g[-1])]
        if split:
            first = (sum_N[split - 1], sum_g[split - 1])
            parts = [first, (sum_N[-1] - first[0], sum_g[-1] - first[1])]
        n = len(parts)
        N, g = np.zeros((n + 2, n + 2)), np.zeros(n + 2)
        for i, (Nk, gk) in enumerate(parts):
            idx = [i, n, n + 1]
            N[np.ix_(idx, idx)] += Nk
            g[idx] += gk
        x = np.linalg.lstsq(N, g, rcond=None)[0]
        return float(g @ x), float(x[1] - x[0]) if split else 0.0

    common, _ = explained(0)
    rest = sum(r[3] for r in rows) - common
    var = rest / max(2 * sum(r[4] for r in rows) - 6 * len(rows) - 3, 1)
    best = (0.0, 0.0, 0)
    for i in range(2, len(rows) - 1):
        more, step = explained(i)
        stat = (more - common) / var if var > 0 else 0.0
        if stat > best[0]:
            best = (stat, step, rows[i][0])
    return best


def _intrinsics_change(
    problem: CalibrationProblem, result: CalibrationResult, lim: Limits
) -> list[Check]:
    """The ``intrinsics`` check per camera: a focal length that changed between parts of the
    session (a focus ring or zoom moved): beyond ``focal_change_stat`` and ``focal_change_rel``."""
    out = []
    for name, c in result.cameras.items():
        if name not in {s.name for s in problem.cameras}:
            continue
        try:
            found = focal_change(
                problem, name, np.asarray(c.K, float), np.asarray(c.distortion, float).reshape(-1)
            )
        except cv2.error:
            found = None
        if found is None:
            continue
        stat, rel, k = found
        ok = stat <= lim.focal_change_stat or abs(rel) <= lim.focal_change_rel
        frame = problem.frames[k].id
        out.append(
            _check(
                "intrinsics",
                ok,
                stat,
                lim.focal_change_stat,
                f"camera {name}: the images alone see its focal length {rel * 100:+.2f} % from "
                f"frame {frame} on at {stat:.1f} (chi-square; limits.focal_change_stat "
                f"{lim.focal_change_stat:g}, limits.focal_change_rel "
                f"{lim.focal_change_rel * 100:g} %)",
                ": the camera's intrinsics changed during the session (focus, zoom or "
                "the lens moved); lock the focus (and zoom) and record the session again",
            )
        )
    return out


# ----------------------------------------------------------------------------- comparison


def displacement_px(
    new: CalibrationResult,
    old: CalibrationResult,
    camera: str,
    distance_m: float,
    region: float = 0.5,
    n: int = 11,
) -> float:
    """The largest image displacement of points at ``distance_m`` in front of ``camera``: an
    ``n x n`` grid over the central ``region`` of the old image cast to rays, carried through the
    old hand-eye and back through the new hand-eye and intrinsics (the intrinsics alone without
    a hand-eye in both)."""
    a, b = old.cameras[camera], new.cameras[camera]
    hw, hh = region * (a.width - 1) / 2, region * (a.height - 1) / 2
    cu, cv = (a.width - 1) / 2, (a.height - 1) / 2
    u, v = np.meshgrid(np.linspace(cu - hw, cu + hw, n), np.linspace(cv - hh, cv + hh, n))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    K_a = np.asarray(a.K, dtype=float)
    rays = undistort_normalised(K_a, a.distortion, px)
    P_cam = np.hstack([rays, np.ones((len(rays), 1))]) * distance_m
    key = hand_eye_names(old.mount, list(old.cameras)).get(camera)
    he_a, he_b = hand_eye_transforms(old), hand_eye_transforms(new)
    Ta = he_a[key].T if key in he_a else None
    Tb = he_b[key].T if key in he_b else None
    if Ta is not None and Tb is not None:
        P_frame = P_cam @ Ta[:3, :3].T + Ta[:3, 3]
        Tb_inv = np.linalg.inv(Tb)
        P_cam_b = P_frame @ Tb_inv[:3, :3].T + Tb_inv[:3, 3]
    else:
        P_cam_b = P_cam
    K_b = np.asarray(b.K, dtype=float)
    proj = project(K_b, b.distortion, P_cam_b)
    return float(np.max(np.linalg.norm(proj - px, axis=1)))


def compare(
    new: CalibrationResult, old: CalibrationResult, lim: Limits | None = None
) -> tuple[list[Check], dict[str, Any]]:
    """The change from the installed calibration ``old``: per parameter in combined sigmas,
    and as a pixel displacement at the working distance (see :func:`displacement_px`)."""
    lim = lim or Limits()
    common = [n for n in new.cameras if n in old.cameras]
    if not common:
        check = Check(
            "installed",
            False,
            None,
            None,
            f"the installed calibration has cameras {list(old.cameras)}, this one "
            f"{list(new.cameras)}; they cannot be compared",
        )
        return [check], {"comparable": False}
    z: dict[str, float] = {}

    def add(key: str, a: float, b: float, sa: float | None, sb: float | None) -> None:
        """``z[key]``: the change ``a - b`` in combined sigmas, where both are known."""
        if sa is not None and sb is not None and np.isfinite(sa) and np.isfinite(sb):
            s = float(np.hypot(sa, sb))
            if s > 0:
                z[key] = abs(a - b) / s

    for n in common:
        a, b = new.cameras[n], old.cameras[n]
        Ka, Kb = np.asarray(a.K), np.asarray(b.K)
        vals = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}
        for p, (i, j) in vals.items():
            add(f"{n}.{p}", Ka[i, j], Kb[i, j], _num(a.std.get(p)), _num(b.std.get(p)))
        da = np.asarray(a.distortion).reshape(-1)
        db = np.asarray(b.distortion).reshape(-1)
        same = distortion_model(da) == distortion_model(db)  # else the displacement compares
        for k, p in enumerate(DISTORTION_MODELS[distortion_model(da)] if same else ()):
            add(f"{n}.{p}", da[k], db[k], _num(a.std.get(p)), _num(b.std.get(p)))
    he_a, he_b = hand_eye_transforms(new), hand_eye_transforms(old)
    pairs = [(k, he_a[k], he_b[k]) for k in he_a if k in he_b]
    pairs += [(k, t, old.rig[k]) for k, t in new.rig.items() if k in old.rig]
    for key, ta, tb in pairs:
        if ta.R is not None and tb.R is not None:
            ang = rotation_angle_deg(ta.R, tb.R)
            add(f"{key}.rot", ang, 0.0, _num(ta.std_rot_deg), _num(tb.std_rot_deg))
        if ta.t_m is not None and tb.t_m is not None:
            dt = float(np.linalg.norm(np.asarray(ta.t_m) - np.asarray(tb.t_m)) * 1000.0)
            add(f"{key}.t", dt, 0.0, _num(ta.std_t_mm), _num(tb.std_t_mm))
    disp = {
        n: displacement_px(new, old, n, lim.working_distance_m, lim.change_region) for n in common
    }
    worst_p = max(z, key=lambda k: z[k]) if z else None
    worst_z = z[worst_p] if worst_p else None
    worst_c = max(disp, key=lambda k: disp[k])
    checks = [
        Check(
            "installed",
            worst_z is None or worst_z <= lim.max_change_sigma,
            worst_z,
            lim.max_change_sigma,
            (
                f"largest change from the installed calibration: {worst_p} by {worst_z:.1f} "
                f"combined sigma (limit {lim.max_change_sigma:g})"
                if worst_z is not None
                else "no uncertainties to compare the installed calibration with"
            ),
        ),
        Check(
            "installed",
            # a displacement counts only beyond the combined noise (docs/UNATTENDED.md)
            disp[worst_c] <= lim.max_change_px
            or (worst_z is not None and worst_z <= lim.max_change_sigma),
            disp[worst_c],
            lim.max_change_px,
            f"camera {worst_c}: points at {lim.working_distance_m:g} m move by up to "
            f"{disp[worst_c]:.2f} px against the installed calibration "
            f"(limit {lim.max_change_px:g} px, when the change is beyond "
            f"{lim.max_change_sigma:g} combined sigma)",
        ),
    ]
    info = {
        "max_sigma": _num(worst_z),
        "max_sigma_parameter": worst_p,
        "max_displacement_px": {k: _num(v) for k, v in disp.items()},
        "sigma": {k: _num(v) for k, v in z.items()},
    }
    return checks, info


def paired_compare(
    new: CalibrationProblem,
    old: CalibrationProblem,
    installed: CalibrationResult,
    px_limit: float,
    region: float = 0.5,
) -> tuple[list[Check], dict[str, Any]]:
    """The paired drift test (:mod:`slidecal.solver.drift`) per camera of the frames of ``new`` at
    robot poses of ``old`` (the installed session): ``drifted`` when the corners' displacement
    field is significant and moves the central ``region`` by more than ``px_limit``.
    ``info["usable"]`` False (with ``info["why"]``, no checks) without enough shared poses."""
    pairs = drift.match_poses(
        [f.T_base_tool for f in new.frames], [f.T_base_tool for f in old.frames]
    )
    if not pairs:
        why = "no robot pose of this session is one of the installed session's poses"
        return [], {"usable": False, "why": why}
    old_names = {c.name for c in old.cameras}
    checks, per, whys = [], {}, []
    for spec in new.cameras:
        cam = spec.name
        if cam not in installed.cameras or cam not in old_names:
            continue
        olds, news, gross = [], [], 0
        for i, j in pairs:
            dn, do = new.frames[i].detections.get(cam), old.frames[j].detections.get(cam)
            if dn is None or do is None:
                continue
            a, b = drift.common_corners(dn.ids, dn.px, do.ids, do.px)
            if len(a) < drift.MIN_CORNERS:
                continue
            if median(np.linalg.norm(b - a, axis=1)) > drift.GROSS_PX:
                gross += 1
                continue
            olds.append(a)
            news.append(b)
        cal = installed.cameras[cam]
        hw, hh = region * (cal.width - 1) / 2, region * (cal.height - 1) / 2
        cu, cv = (cal.width - 1) / 2, (cal.height - 1) / 2
        try:
            fld = drift.displacement_field(
                olds, news, np.asarray(cal.K, float), (cu - hw, cv - hh, cu + hw, cv + hh)
            )
        except DegenerateError as e:
            moved = (
                f"; at {gross} the corners moved by more than {drift.GROSS_PX:g} px (the board "
                "or the camera moved far)"
                if gross
                else ""
            )
            whys.append(f"camera {cam}: {len(pairs)} poses shared{moved}; {e}")
            continue
        bad = fld.drifted(px_limit)
        eq = fld.equivalent
        s = fld.mean_px
        checks.append(
            _check(
                "paired",
                not bad,
                fld.max_px,
                px_limit,
                f"camera {cam}: at {fld.n_poses} of the installed session's robot poses its "
                f"corners moved by up to {fld.max_px:.2f} px (limit {px_limit:g} px) at "
                f"{fld.max_z:.1f} sigma (limit {drift.Z_LIMIT:g}): shift ({s[0]:+.2f}, "
                f"{s[1]:+.2f}) px, scale {s[2]:+.2f} px, turn {s[3]:+.2f} px at "
                f"{fld.radius_px:.0f} px from the principal point; as the camera: principal "
                f"point ({eq['cx_px']:+.2f}, {eq['cy_px']:+.2f}) px or a rotation of "
                f"{eq['rotation_deg']:.3f} deg, focal length {eq['f_rel'] * 100:+.3f} %",
                "; the camera changed or the board moved (a paired comparison cannot tell "
                "them apart: if the board was moved, calibrate and install anew)",
            )
        )
        per[cam] = {
            "poses": fld.n_poses,
            "corners": fld.n_corners,
            "max_px": _num(fld.max_px),
            "max_z": _num(fld.max_z),
            "field_px": [_num(v) for v in fld.mean_px],
            "field_std_px": [_num(v) for v in fld.std_px],
            "radius_px": _num(fld.radius_px),
            "corner_noise_px": _num(fld.corner_noise_px),
            "pose_scatter_px": _num(fld.pose_scatter_px),
            "equivalent": {k: _num(v) for k, v in eq.items()},
        }
    if not checks:
        return [], {"usable": False, "why": "; ".join(whys) or "no camera in common"}
    info: dict[str, Any] = {"usable": True, "shared_poses": len(pairs), "cameras": per}
    if whys:
        info["why"] = "; ".join(whys)
    return checks, info


def check_residuals(
    residual_rms_px: Mapping[str, float],
    expected_rms_px: Mapping[str, float],
    drift_px: Mapping[str, float],
    lim: Limits,
    n_frames: int,
) -> list[Check]:
    """``slidecal check``'s test per camera: the images disagree with the installed calibration
    beyond the limits (``residual_rms_px``, ``expected_rms_px`` and ``drift_px``)."""
    checks = []
    for n, r in residual_rms_px.items():
        ratio = r / expected_rms_px[n] if expected_rms_px[n] > 0 else float("inf")
        ok = ratio <= lim.check_max_rms_ratio or drift_px[n] <= lim.check_max_px
        checks.append(
            Check(
                "check",
                bool(ok),
                _num(ratio),
                lim.check_max_rms_ratio,
                f"camera {n}: residual rms {r:.3f} px at {n_frames} known robot poses is "
                f"{ratio:.2f} times what the installed calibration explains "
                f"({expected_rms_px[n]:.3f} px; limit {lim.check_max_rms_ratio:g}); drift "
                f"{drift_px[n]:.2f} px (limit {lim.check_max_px:g} px)",
            )
        )
    return checks

"""Real robot data: slidecal on the public KUKA sessions of Ali et al. (Sensors 2019).

``python -m tests.bench public --data DIR`` (writes docs/results/PUBLIC_DATA.md): ``DIR`` holds the
data set's
folders ``kuka_1``, ``kuka_2`` and ``kuka_3`` as the authors publish them (images, and
``RobotPosesVec.txt``: one row-major 4 x 4 ``T_base_tool`` in metres per image, image ``k``
with row ``k``). The data is not shipped with slidecal (its licence does not say it may be).

Each set becomes a session as a user writes one from the public contract (docs/FORMATS.md):
the robot poses as transforms (``{R, t_m}``), the images by path, the target as counted on the
images, no tolerance given (a real board's defaults). ``slidecal solve`` runs on it as a user
runs it (the console entry, default options), and on the largest group of frames that share
one orientation (13 translation-only frames in kuka_1 and kuka_3). kuka_1 and kuka_3 are the
same camera on the same arm in front of two boards: their intrinsics must agree within their
reported uncertainty, and each translation-only subset must agree with its full session;
their hand-eye likewise (the same mount). Each full session's hand-eye is compared with
OpenCV's closed forms (``cv2.calibrateHandEye``, Park and Daniilidis) on OpenCV's own
calibration, and each full session is solved again with the robot accuracy it learned given
as options (no linear field of the arm's error modelled) to show what that field moves, and
again with two of its frames left out (``--leave-out`` sessions per set): how much the verdict
and the uncertainty rest on the frames a session happened to record.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import yaml

from slidecal.mocks.truth import hand_eye_errors
from slidecal.routines.cli import main as cli
from slidecal.routines.results_io import read_result, scale_check_summary
from slidecal.routines.session import target_from_dict
from slidecal.solver.detect import detect
from slidecal.solver.errors import InputError
from slidecal.solver.model import orientation_groups
from tests.bench.report import RESULTS, publish_report, report_header

#: The sets: the target as counted on the images (the ChArUco's marker side measured at 0.75 of
#: its square; its dictionary the one whose ids 0-53 decode) and the image file pattern
SETS = {
    "kuka_1": (
        {"kind": "chessboard", "squares_x": 29, "squares_y": 18, "square_size_m": 0.02},
        "{:02d}.png",
    ),
    "kuka_2": (
        {"kind": "chessboard", "squares_x": 25, "squares_y": 18, "square_size_m": 0.015},
        "im_{:02d}.bmp",
    ),
    "kuka_3": (
        {
            "kind": "charuco",
            "squares_x": 12,
            "squares_y": 9,
            "square_size_m": 0.06,
            "marker_size_m": 0.045,
            "dictionary": "DICT_5X5_100",
        },
        "{:02d}.png",
    ),
}
#: (a, b): sessions of one camera whose intrinsics must agree
SAME_CAMERA = (("kuka_1", "kuka_3"),)


def write_session(
    name: str, data: Path, out: Path, frames: list[int] | None = None, options: dict | None = None
) -> Path:
    """Session ``out`` of set ``name`` (frames numbered from 1; all by default; ``options``: the
    session file's, none by default)."""
    target, pattern = SETS[name]
    poses = np.loadtxt(data / name / "RobotPosesVec.txt").reshape(-1, 4, 4)
    (out / "images").mkdir(parents=True, exist_ok=True)
    first = cv2.imread(str(data / name / pattern.format(1)), cv2.IMREAD_UNCHANGED)
    if first is None:
        raise InputError(f"{data / name / pattern.format(1)} is not readable; check --data")
    h, w = first.shape[:2]
    entries = []
    for k in frames or range(1, len(poses) + 1):
        src = data / name / pattern.format(k)
        dst = out / "images" / src.name
        if not dst.exists():
            try:
                os.link(src, dst)
            except OSError:
                shutil.copyfile(src, dst)
        T = poses[k - 1]
        entries.append(
            {
                "id": k,
                "T_base_tool": {"R": T[:3, :3].tolist(), "t_m": T[:3, 3].tolist()},
                "images": {"cam": f"images/{src.name}"},
            }
        )
    doc = {
        "format": "slidecal.session/1",
        "mount": "eye_in_hand",
        "target": target,
        "cameras": [{"name": "cam", "width": w, "height": h}],
        "frames": entries,
    }
    if options:
        doc["options"] = options
    (out / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return out


def translation_frames(name: str, data: Path) -> list[int]:
    """The frames (from 1) of the set's largest group sharing one orientation."""
    poses = np.loadtxt(data / name / "RobotPosesVec.txt").reshape(-1, 4, 4)
    groups = orientation_groups(poses)
    biggest = int(np.argmax(np.bincount(groups)))
    return [int(i) + 1 for i in np.flatnonzero(groups == biggest)]


def solve(session: Path) -> tuple[int, dict, float]:
    """``slidecal solve SESSION`` as a user runs it: exit code, the result file, seconds."""
    out = session / "result.yaml"
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        code = cli(["solve", str(session), "--out", str(out), "--quiet"])
    dt = time.perf_counter() - t0
    path = out if out.is_file() else session / "rejected" / "result.yaml"
    return code, (read_result(path) if path.is_file() else None), dt


def _row(label: str, code: int, r, dt: float) -> str:  # noqa: ANN001 - CalibrationResult
    if r is None:
        return f"| {label} | {code} | | | | | | | | {dt:.1f} |"
    c = r.cameras["cam"]
    he = r.hand_eye
    bow = (
        f"{r.board.bow_mm[0]:+.3f} +- {r.board.bow_std_mm[0]:.3f}, "
        f"{r.board.bow_mm[1]:+.3f} +- {r.board.bow_std_mm[1]:.3f}"
        if r.board is not None
        else ""
    )
    ra = r.robot_accuracy
    arm = f"{ra.translation_mm:.2f} mm, {ra.rotation_deg:.3f} deg" if ra is not None else ""
    t = f"{he.std_t_mm:.2f}" if he is not None and he.std_t_mm is not None else "n/a"
    sc = scale_check_summary(r.scale_checks)
    scale = f"{sc['median_ratio']:.4f} over {sc['n']} moves" if sc else "not checked"
    return (
        f"| {label} | {code} | {c.K[0, 0]:.2f} +- {c.std['fx']:.2f} | "
        f"{c.K[0, 2]:.2f} +- {c.std['cx']:.2f} | {c.K[1, 2]:.2f} +- {c.std['cy']:.2f} | {bow} | "
        f"{arm} | {scale} | {he.std_rot_deg:.3f} deg, {t} mm | {dt:.1f} |"
    )


def _z(a, b, p: str, index: tuple[int, int]) -> tuple[float, float]:  # noqa: ANN001
    """(difference, difference / combined std) of intrinsic ``p`` between two results."""
    ca, cb = a.cameras["cam"], b.cameras["cam"]
    d = float(ca.K[index] - cb.K[index])
    return d, d / float(np.hypot(ca.std[p], cb.std[p]))


def _z_subset(sub, full, p: str, index: tuple[int, int]) -> tuple[float, float]:  # noqa: ANN001
    """(difference, difference / the subset's std): a subset against its own full session,
    whose estimate shares the subset's frames (its std is not independent)."""
    d = float(sub.cameras["cam"].K[index] - full.cameras["cam"].K[index])
    return d, d / float(sub.cameras["cam"].std[p])


INTRINSICS = {"fx": (0, 0), "cx": (0, 2), "cy": (1, 2)}


def _peer_row(name: str, peer: Peer | None) -> str:
    if peer is None:
        return f"| {name} | the board in fewer than 3 frames | | | | |"
    K, rms = peer.K, peer.rms_px
    return f"| {name} | {K[0, 0]:.2f} | {K[1, 1]:.2f} | {K[0, 2]:.2f} | {K[1, 2]:.2f} | {rms:.3f} |"


class Peer(NamedTuple):
    """OpenCV's answer on all of a set's frames."""

    K: np.ndarray
    rms_px: float
    #: ``cv2.calibrateHandEye`` method name -> its ``T_tool_cam`` (4 x 4) from OpenCV's own
    #: board poses and the robot's; empty when the frames share fewer than 3 orientations
    hand_eye: dict[str, np.ndarray]


#: The closed forms compared with slidecal's hand-eye
HAND_EYE_METHODS = {"Park": cv2.CALIB_HAND_EYE_PARK, "Daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS}


def opencv_reference(name: str, data: Path) -> Peer | None:
    """The peer's answer on all of a set's frames: ``cv2.calibrateCamera`` (default flags: k1,
    k2, p1, p2, k3; no robot, the board as described) on slidecal's detections, and
    ``cv2.calibrateHandEye`` on its board poses with the robot's; None when fewer than three
    frames show the board."""
    spec, pattern = SETS[name]
    target = target_from_dict(dict(spec), name)
    poses = np.loadtxt(data / name / "RobotPosesVec.txt").reshape(-1, 4, 4)
    obj, img, used, size = [], [], [], None
    for k in range(1, len(poses) + 1):
        image = cv2.imread(str(data / name / pattern.format(k)), cv2.IMREAD_UNCHANGED)
        size = (image.shape[1], image.shape[0])
        d = detect(image, target).detection
        if len(d.ids) >= 6:
            obj.append(target.points_m[d.ids].astype(np.float32))
            img.append(d.px.astype(np.float32).reshape(-1, 1, 2))
            used.append(k - 1)
    if len(obj) < 3:
        return None
    rms, K, _, rvecs, tvecs = cv2.calibrateCamera(obj, img, size, None, None)
    hand_eye = {}
    if len(set(orientation_groups(poses[used]).tolist())) >= 3:
        for method, flag in HAND_EYE_METHODS.items():
            R, t = cv2.calibrateHandEye(
                [poses[i][:3, :3] for i in used],
                [poses[i][:3, 3] for i in used],
                [cv2.Rodrigues(r)[0] for r in rvecs],
                list(tvecs),
                method=flag,
            )
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, np.ravel(t)
            hand_eye[method] = T
    return Peer(K, float(rms), hand_eye)


def _hand_eye_cells(a, b, other=None) -> tuple[str, str]:  # noqa: ANN001 - results
    """Table cells of result ``a``'s hand-eye against ``b`` (a result or a 4 x 4): rotation
    angle and translation distance, each with its Mahalanobis distance under ``a``'s
    covariance, plus result ``other``'s where given (n/a where a translation is not reported)."""
    if isinstance(b, np.ndarray):
        T, b_t = b, True
    else:
        T, b_t = np.eye(4), b.hand_eye.t_m is not None
        T[:3, :3] = b.hand_eye.R
        T[:3, 3] = b.hand_eye.t_m if b_t else 0.0
    errors = hand_eye_errors(a, T)
    extra = hand_eye_errors(other, T) if other is not None else {}
    cells = []
    for key, scale, unit in (("rot", np.degrees(1.0), "deg"), ("t", 1000.0, "mm")):
        if (
            key not in errors
            or (key == "t" and not b_t)
            or (other is not None and key not in extra)
        ):
            cells.append("n/a")
            continue
        d, C = errors[key]
        C = C + extra[key][1] if other is not None else C
        z = float(np.sqrt(d @ np.linalg.solve(C, d)))
        cells.append(f"{scale * np.linalg.norm(d):.{3 if key == 'rot' else 2}f} {unit} ({z:.2f})")
    return cells[0], cells[1]


def main(argv: list[str] | None = None) -> int:
    """Entry point (``python -m tests.bench public``)."""
    ap = argparse.ArgumentParser(prog="bench_public", description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, help="the folder holding kuka_1, kuka_2, kuka_3")
    ap.add_argument("--out", default=str(RESULTS / "PUBLIC_DATA.md"), help="the report to write")
    ap.add_argument(
        "--leave-out",
        dest="leave_out",
        type=int,
        default=LEAVE_OUT_SUBSETS,
        help="sessions per set with two frames left out (0: none)",
    )
    args = ap.parse_args(argv)
    data = Path(args.data)
    missing = [n for n in SETS if not (data / n / "RobotPosesVec.txt").is_file()]
    if missing:
        raise InputError(
            f"--data {data}: no {missing[0]}/RobotPosesVec.txt; give the folder holding the "
            "public data set's kuka_1, kuka_2 and kuka_3"
        )
    t0 = time.time()
    peer = {name: opencv_reference(name, data) for name in SETS}
    results, rows, left = {}, [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in SETS:
            code, r, dt = solve(write_session(name, data, Path(tmp) / name))
            results[name] = r
            rows.append(_row(f"{name}, all {r and len(r.residuals_px)} frames", code, r, dt))
            if r is not None and r.robot_accuracy is not None:
                fixed = {  # the levels learned, taken as given: no linear field of the arm's error
                    "robot_noise_mm": r.robot_accuracy.translation_mm,
                    "robot_noise_deg": r.robot_accuracy.rotation_deg,
                    "estimate_robot_noise": False,
                }
                session = write_session(name, data, Path(tmp) / f"{name}_fixed", options=fixed)
                results[f"{name}_fixed"] = solve(session)[1]
            if args.leave_out > 0 and r is not None:
                left[name] = leave_out_rows(name, data, Path(tmp), r, args.leave_out)
            if name == "kuka_2":
                continue
            sub = translation_frames(name, data)
            code, r, dt = solve(write_session(name, data, Path(tmp) / f"{name}_t", sub))
            results[f"{name}_t"] = r
            rows.append(_row(f"{name}, its {len(sub)} frames at one orientation", code, r, dt))
    shown = ["--data", "DIR", *(a for a in argv or [] if a.startswith("--out"))]  # no local path
    if args.leave_out != LEAVE_OUT_SUBSETS:
        shown += ["--leave-out", str(args.leave_out)]
    lines = report_header(
        "Real robot data: public KUKA sessions", "public", shown, time.time() - t0
    )
    lines += [
        "Sessions written from the public contract (robot poses as `{R, t_m}` transforms, the "
        "images by path, no tolerance given for the board) and solved by `slidecal solve` "
        "with default options (tests/bench/public.py says how each set becomes a session). "
        "kuka_1: chessboard of 29 x 18 squares of 20 mm, 1928 x 1208 colour; kuka_2: "
        "chessboard of 25 x 18 squares of 15 mm, 1920 x 1200 grey, a classic session (every "
        "orientation different); kuka_3: ChArUco board of 12 x 9 squares of 60 mm, the camera "
        "and arm of kuka_1. Exit 0: accepted by the verdict. The hand-eye column: one-sigma of "
        "`T_tool_cam` (rotation; translation, n/a where one orientation cannot tell it). "
        "DIR: the folder holding the data set's kuka_1, kuka_2 and kuka_3 (Ali, Suominen, "
        "Gotchev, Morales: Methods for simultaneous robot-world-hand-eye calibration, Sensors "
        "19(12) 2837, 2019; not shipped). What the board's bow and print do: "
        "docs/ROBOT_ACCURACY.md, 'The board'. Camera/robot scale: the median ratio of the "
        "moves' lengths as the camera and the robot tell them (the verdict's scale test); "
        "kuka_2's geometry does not pin it (docs/METHOD.md Sec. 3), and its result says so.",
        "",
        "| session | exit | fx (px) | cx (px) | cy (px) | bow x, y (mm) | robot accuracy "
        "learned | camera/robot scale | hand-eye std | solve s |",
        "| --- | ---: | ---: | ---: | ---: | --- | --- | --- | --- | ---: |",
        *rows,
        "",
        "The peer on the same detections: OpenCV's `calibrateCamera` on all of a set's frames "
        "(default flags; no robot; the board taken as flat and exact, as every such tool takes "
        "it). slidecal's full sessions are reported halfway between the readings 'the misfit "
        "the images show is the board's bow' and 'it is not' (docs/ROBOT_ACCURACY.md), "
        "the spread of the two in their std; a translation-only session's focal length rests "
        "on the robot's moves instead of the board.",
        "",
        "| set | fx (px) | fy (px) | cx (px) | cy (px) | rms (px) |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
        *(_peer_row(name, p) for name, p in peer.items()),
        "",
        "## Agreement",
        "",
        "| compared | fx | cx | cy |",
        "| --- | --- | --- | --- |",
    ]
    for a, b in SAME_CAMERA:
        if results.get(a) and results.get(b):
            cells = [
                "{:+.2f} px ({:+.2f} std)".format(*_z(results[a], results[b], p, ix))
                for p, ix in INTRINSICS.items()
            ]
            lines.append(
                f"| {a} against {b} (one camera, two boards) | " + " | ".join(cells) + " |"
            )
    for name in ("kuka_1", "kuka_3"):
        sub, full = results.get(f"{name}_t"), results.get(name)
        if sub and full:
            cells = [
                "{:+.2f} px ({:+.2f} of its std)".format(*_z_subset(sub, full, p, ix))
                for p, ix in INTRINSICS.items()
            ]
            rel = 100.0 * (sub.cameras["cam"].K[0, 0] / full.cameras["cam"].K[0, 0] - 1.0)
            cells[0] += f", {rel:+.3f} %"
            lines.append(
                f"| {name}'s one-orientation frames against all its frames | "
                + " | ".join(cells)
                + " |"
            )
        if sub and peer[name] is not None:
            K, c = peer[name].K, sub.cameras["cam"]
            cells = [
                f"{c.K[ix] - K[ix]:+.2f} px ({(c.K[ix] - K[ix]) / c.std[p]:+.2f} of its std)"
                for p, ix in INTRINSICS.items()
            ]
            cells[0] += f", {100.0 * (c.K[0, 0] / K[0, 0] - 1.0):+.3f} %"
            lines.append(
                f"| {name}'s one-orientation frames against OpenCV on all its frames | "
                + " | ".join(cells)
                + " |"
            )
    lines += _hand_eye_agreement(results, peer)
    if left:
        lines += _leave_out_section(left)
    return publish_report("\n".join(lines) + "\n", args.out)


#: Sessions per set with frames left out (``--leave-out``), and how many each leaves out
LEAVE_OUT_SUBSETS = 8
LEAVE_OUT_FRAMES = 2


class LeftOut(NamedTuple):
    """One session of a set with frames left out, solved as a user solves it."""

    gone: list[int]  # the frames left out (from 1)
    code: int
    std_t_mm: float
    std_rot_deg: float
    dfx_px: float  # fx less the full session's
    dt_mm: float  # the hand-eye translation's distance from the full session's


def leave_out_rows(name: str, data: Path, tmp: Path, full, n: int) -> list[LeftOut]:  # noqa: ANN001
    """``n`` sessions of set ``name``, each with :data:`LEAVE_OUT_FRAMES` frames drawn at random
    (seeded by the set) left out: how much a session's verdict and uncertainty rest on which
    frames it happened to record."""
    total = len(np.loadtxt(data / name / "RobotPosesVec.txt").reshape(-1, 16))
    rng = np.random.default_rng(int(name.rsplit("_", 1)[-1]))
    out = []
    for j in range(n):
        gone = sorted(int(i) for i in rng.choice(np.arange(1, total + 1), LEAVE_OUT_FRAMES, False))
        keep = [i for i in range(1, total + 1) if i not in gone]
        code, r, _ = solve(write_session(name, data, tmp / f"{name}_left{j}", keep))
        if r is None or r.hand_eye is None:
            out.append(LeftOut(gone, code, np.nan, np.nan, np.nan, np.nan))
            continue
        he, fhe = r.hand_eye, full.hand_eye
        out.append(
            LeftOut(
                gone,
                code,
                float(he.std_t_mm if he.std_t_mm is not None else np.nan),
                float(he.std_rot_deg if he.std_rot_deg is not None else np.nan),
                float(r.cameras["cam"].K[0, 0] - full.cameras["cam"].K[0, 0]),
                float(1000.0 * np.linalg.norm(he.t_m - fhe.t_m)),
            )
        )
    return out


def _leave_out_section(left: dict[str, list[LeftOut]]) -> list[str]:
    """The table of the sessions with frames left out (:func:`leave_out_rows`)."""

    def span(xs: list[float], fmt: str) -> str:
        xs = [x for x in xs if np.isfinite(x)]
        return f"{min(xs):{fmt}} to {max(xs):{fmt}}" if xs else "n/a"

    lines = [
        "",
        "## Sessions with frames left out",
        "",
        f"Each set solved again {len(next(iter(left.values())))} times, each time with "
        f"{LEAVE_OUT_FRAMES} of its frames drawn at random left out (seeded by the set), as a "
        "session that happened to record fewer: how far its verdict and its uncertainty rest "
        "on the frames it got. The verdict's default limit on the hand-eye translation's "
        "one-sigma (`limits.hand_eye_t_std_mm`, docs/UNATTENDED.md) is set from these figures.",
        "",
        "| set | sessions | exit 0 | hand-eye std, rotation (deg) | hand-eye std, translation "
        "(mm) | fx less the full session's (px) | hand-eye translation from the full "
        "session's (mm) | not accepted |",
        "| --- | ---: | ---: | --- | --- | --- | --- | --- |",
    ]
    for name, rows in left.items():
        bad = [f"frames {r.gone} left out: exit {r.code}" for r in rows if r.code != 0]
        lines.append(
            f"| {name} | {len(rows)} | {sum(r.code == 0 for r in rows)} | "
            f"{span([r.std_rot_deg for r in rows], '.3f')} | "
            f"{span([r.std_t_mm for r in rows], '.2f')} | "
            f"{span([r.dfx_px for r in rows], '+.2f')} | "
            f"{span([r.dt_mm for r in rows], '.2f')} | {'; '.join(bad) or '-'} |"
        )
    return lines


def _hand_eye_agreement(results: dict, peer: dict[str, Peer | None]) -> list[str]:
    """The hand-eye table: the same mount seen twice, each subset against its full session,
    OpenCV's closed forms against slidecal on each full session."""
    rows = []
    for a, b in SAME_CAMERA:
        if results.get(a) and results.get(b):
            cells = _hand_eye_cells(results[b], results[a], other=results[a])
            rows.append(
                f"| {b} against {a} (one camera and mount, two boards) | "
                + " | ".join(cells)
                + " |"
            )
    for name in ("kuka_1", "kuka_3"):
        sub, full = results.get(f"{name}_t"), results.get(name)
        if sub and full:
            cells = _hand_eye_cells(sub, full)
            rows.append(
                f"| {name}'s one-orientation frames against all its frames | "
                + " | ".join(cells)
                + " |"
            )
    for name in SETS:
        p = peer.get(name)
        for method, T in (p.hand_eye if p is not None else {}).items():
            for key, how in ((name, ""), (f"{name}_fixed", ", its levels fixed")):
                if results.get(key):
                    cells = _hand_eye_cells(results[key], T)
                    rows.append(
                        f"| OpenCV's {method} against slidecal{how} on {name} | "
                        + " | ".join(cells)
                        + " |"
                    )
    return [
        "",
        "## Hand-eye agreement",
        "",
        "`T_tool_cam` compared: the angle of the rotation between two estimates and the distance "
        "between their translations, each with its Mahalanobis distance under the covariance "
        "reported for it in brackets (the two results' summed for independent sessions; the "
        "subset's alone against its full session, which shares its frames; slidecal's alone "
        "against OpenCV's closed forms, whose own error it leaves out). Three components: an "
        "estimate whose covariance is right exceeds 2.80 in 5 % of cases and 3.37 in 1 %. "
        "OpenCV's closed forms start from its own intrinsics and board poses (`calibrateCamera` "
        "above, then `calibrateHandEye`) and take the robot's poses as exact. 'its levels "
        "fixed': the same session solved with the robot accuracy slidecal learned on it given "
        "as options (`robot_noise_mm`, `robot_noise_deg`, `estimate_robot_noise: false`), so "
        "that no linear field of the arm's error over its positions is modelled, as the "
        "closed forms model none. A classic session (kuka_2) learns one over the whole "
        "session and is reported halfway between the readings with and without it, their "
        "spread in its covariance (docs/ROBOT_ACCURACY.md, 'Two readings of the field'); "
        "'its levels fixed' is the reading without it.",
        "",
        "| compared | rotation | translation |",
        "| --- | --- | --- |",
        *rows,
    ]

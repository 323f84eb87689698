"""The morning report of a run: ``report.html`` (self-contained) and ``report.png``: the verdict,
per camera the magnified residuals on the coverage grid and the projection-uncertainty map,
the robot's accuracy per frame and the difference from the installed calibration."""

from __future__ import annotations

import base64
import html
from pathlib import Path

import cv2
import numpy as np

from slidecal.routines.ops.verdict import Verdict, coverage_fraction, uncertainty_map
from slidecal.routines.schema import write_atomic
from slidecal.solver.calibrate import pnp_pose
from slidecal.solver.camera import project
from slidecal.solver.drift import T_cam_board, hand_eye_T
from slidecal.solver.errors import InputError
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.result import CalibrationResult

REPORT_HTML = "report.html"
REPORT_PNG = "report.png"
PANEL_W = 560
_COLOURS = {
    "accepted": (60, 160, 60),
    "ok": (60, 160, 60),
    "drifted": (0, 140, 230),
    "rejected": (40, 40, 210),
}
_FONT = cv2.FONT_HERSHEY_SIMPLEX
#: unfiltered rows, zlib's default strategy: these drawings' PNGs sooner and smaller than by default
_PNG = [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_DEFAULT]
if hasattr(cv2, "IMWRITE_PNG_FILTER"):  # an option from OpenCV 4.11
    _PNG += [cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]


def _board_poses(
    result: CalibrationResult, problem: CalibrationProblem, camera: str
) -> dict[int, np.ndarray]:
    """``T_cam_board`` per frame id: the solved chain (robot pose, hand-eye, target, rig)
    when it is fully determined, else each image's own pose from the estimated intrinsics."""
    cam = result.cameras[camera]
    K, d = np.asarray(cam.K, float), np.asarray(cam.distortion, float).reshape(-1)
    X = _hand_eye(result, camera)
    out: dict[int, np.ndarray] = {}
    pts = problem.target.points_m
    for fr in problem.frames:
        det = fr.detections.get(camera)
        if det is None or len(det.ids) < 4:
            continue
        if X is not None and fr.T_base_tool is not None:
            out[fr.id] = T_cam_board(result.mount, X, fr.T_base_tool, result.T_target.T)
            continue
        T = pnp_pose(K, d, pts[det.ids], np.asarray(det.px))
        if T is not None:
            out[fr.id] = T
    return out


def _hand_eye(result: CalibrationResult, camera: str) -> np.ndarray | None:
    """The camera's hand-eye when it and the target pose are both determined (the residuals
    through the chain), else None."""
    if result.T_target is None or result.T_target.T is None:
        return None
    try:
        return hand_eye_T(result, camera)
    except InputError:
        return None


def residual_vectors(
    result: CalibrationResult, problem: CalibrationProblem, camera: str
) -> tuple[np.ndarray, np.ndarray]:
    """(detected px (N, 2), detected minus projected px (N, 2)) of every corner of a camera."""
    cam = result.cameras[camera]
    K, d = np.asarray(cam.K, float), np.asarray(cam.distortion, float).reshape(-1)
    poses = _board_poses(result, problem, camera)
    pts = problem.target.points_m
    at, P = [np.zeros((0, 2))], [np.zeros((0, 3))]
    for fr in problem.frames:
        det = fr.detections.get(camera)
        if fr.id in poses and det is not None:
            T = poses[fr.id]
            P.append(pts[det.ids] @ T[:3, :3].T + T[:3, 3])
            at.append(np.asarray(det.px, float))
    px = np.vstack(at)
    return px, px - project(K, d, np.vstack(P)) if len(px) else np.zeros((0, 2))


def _text(img: np.ndarray, s: str, org: tuple[int, int], scale=0.5, colour=(30, 30, 30), th=1):
    cv2.putText(img, s, org, _FONT, scale, colour, th, cv2.LINE_AA)


def residual_panel(
    result: CalibrationResult, problem: CalibrationProblem, camera: str, grid=(8, 6)
) -> np.ndarray:
    """The image area (``PANEL_W`` wide): coverage cells shaded by corner count, residual
    vectors magnified (the scale bar says by how much)."""
    cam = result.cameras[camera]
    s = PANEL_W / cam.width
    H = int(round(cam.height * s))
    img = np.full((H + 40, PANEL_W, 3), 255, np.uint8)
    frac, counts = coverage_fraction(problem, camera, grid)
    nx, ny = grid
    top = counts.max() if counts.size else 1
    for iy in range(ny):
        for ix in range(nx):
            c = counts[iy, ix]
            shade = 255 - int(90 * c / top) if c > 0 else 255
            col = (shade, 255, shade) if c > 0 else (225, 225, 245)
            p0 = (int(ix * PANEL_W / nx), int(iy * H / ny))
            p1 = (int((ix + 1) * PANEL_W / nx) - 1, int((iy + 1) * H / ny) - 1)
            cv2.rectangle(img, p0, p1, col, -1)
            cv2.rectangle(img, p0, p1, (200, 200, 200), 1)
    at, res = residual_vectors(result, problem, camera)
    mag = 1.0
    if len(res):
        rms = float(np.sqrt(np.mean(np.sum(res**2, 1))))
        mag = 12.0 / max(rms * s, 1e-9)  # about 12 display pixels for an rms residual
        mag = float(10 ** np.floor(np.log10(mag)))
        a = (at * s).astype(np.int32)
        b = ((at + res * mag) * s).astype(np.int32)
        cv2.polylines(img, list(np.stack([a, b], 1)), False, (40, 40, 200), 1, cv2.LINE_AA)
        for dx, dy in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):  # cv2.circle's radius-1 dot
            x, y = a[:, 0] + dx, a[:, 1] + dy
            keep = (x >= 0) & (x < PANEL_W) & (y >= 0) & (y < H + 40)
            img[y[keep], x[keep]] = (90, 90, 90)
        chained = _hand_eye(result, camera) is not None
        through = "the measured robot poses" if chained else "each image's pose"
        _text(
            img,
            f"{camera}: residuals via {through} x{mag:g}, rms {rms:.3f} px; "
            f"{frac * 100:.0f} % of cells",
            (6, H + 25),
            0.42,
        )
    return img


def uncertainty_panel(result: CalibrationResult, camera: str) -> np.ndarray | None:
    """The projection-uncertainty map as a colour image with its range written under it."""
    m = uncertainty_map(result, camera)
    if m is None:
        return None
    cam = result.cameras[camera]
    H = int(round(cam.height * PANEL_W / cam.width))
    lo, hi = float(m.min()), float(m.max())
    norm = ((m - lo) / (hi - lo + 1e-12) * 255).astype(np.uint8)
    big = cv2.resize(norm, (PANEL_W, H), interpolation=cv2.INTER_CUBIC)
    col = cv2.applyColorMap(big, cv2.COLORMAP_VIRIDIS)
    img = np.full((H + 40, PANEL_W, 3), 255, np.uint8)
    img[:H] = col
    _text(
        img, f"{camera}: projection one-sigma {lo:.3g} (dark) to {hi:.3g} px (bright)", (6, H + 25)
    )
    return img


def robot_panel(result: CalibrationResult) -> np.ndarray | None:
    """The robot's pose error per frame (bars, mm), when the solver estimated it."""
    ra = result.robot_accuracy
    if ra is None or not ra.worst_frames:
        return None
    frames = sorted(ra.worst_frames)
    img = np.full((220, PANEL_W, 3), 255, np.uint8)
    top = max(f[1] for f in frames) or 1.0
    x0, y0 = 70, 160  # the axes' origin
    w = max(2, (PANEL_W - x0 - 10) // len(frames))
    for k, (fid, t_mm, _deg) in enumerate(frames):
        h = int(140 * t_mm / top)
        x = x0 + 2 + k * w
        cv2.rectangle(img, (x, y0 - h), (x + w - 2, y0), (180, 120, 60), -1)
        if k in (0, len(frames) - 1) or len(frames) <= 12:
            _text(img, str(fid), (x, y0 + 14), 0.35)
    cv2.line(img, (x0, y0), (PANEL_W - 8, y0), (30, 30, 30), 1)
    cv2.line(img, (x0, y0), (x0, y0 - 145), (30, 30, 30), 1)
    for v, y in ((0.0, y0), (top, y0 - 140)):
        cv2.line(img, (x0 - 4, y), (x0, y), (30, 30, 30), 1)
        _text(img, f"{v:.3f}", (6, y + 4), 0.35)
    _text(img, "mm", (6, y0 - 70), 0.35)
    _text(img, "frame id", (PANEL_W - 70, y0 + 28), 0.35)
    _text(
        img,
        f"pose correction per frame; learned {ra.translation_mm:.3f} mm, "
        f"{ra.rotation_deg:.4f} deg rms per axis",
        (6, 210),
        0.42,
    )
    return img


def banner(verdict: Verdict, width: int = PANEL_W * 2) -> np.ndarray:
    """The verdict in its colour and up to six reasons."""
    lines = [c.message for c in verdict.reasons][:6]
    img = np.full((60 + 22 * len(lines), width, 3), 255, np.uint8)
    cv2.rectangle(img, (0, 0), (width, 44), _COLOURS.get(verdict.verdict, (80, 80, 80)), -1)
    _text(img, f"{verdict.command}: {verdict.verdict.upper()}", (10, 32), 0.9, (255, 255, 255), 2)
    for k, line in enumerate(lines):
        _text(img, line[:150], (10, 64 + 22 * k), 0.42)
    return img


def _png(img: np.ndarray, what: str = "a report image") -> bytes:
    ok, buf = cv2.imencode(".png", img, _PNG)
    if not ok:
        raise ValueError(f"OpenCV could not encode {what}")
    return buf.tobytes()


def write_report(
    session_dir: str | Path,
    result: CalibrationResult,
    verdict: Verdict,
    problem: CalibrationProblem,
    installed: CalibrationResult | None = None,
    summary: str | None = None,
) -> Path:
    """Write ``report.png`` and ``report.html`` into ``session_dir``; return the HTML's path."""
    d = Path(session_dir)
    panels: list[tuple[str, np.ndarray]] = []
    for name in result.cameras:
        panels.append(
            (f"Residuals and coverage, camera {name}", residual_panel(result, problem, name))
        )
        u = uncertainty_panel(result, name)
        if u is not None:
            panels.append((f"Projection uncertainty, camera {name}", u))
    rp = robot_panel(result)
    if rp is not None:
        panels.append(("Robot accuracy per frame", rp))
    images = [p for _, p in panels]
    rows = [[banner(verdict)]] + [images[k : k + 2] for k in range(0, len(images), 2)]
    heights = [max(p.shape[0] for p in row) for row in rows]
    png = np.full((sum(heights), PANEL_W * 2, 3), 255, np.uint8)  # the panels two a row, on white
    for row, y in zip(rows, np.cumsum([0, *heights[:-1]]), strict=True):
        for k, p in enumerate(row):
            png[y : y + p.shape[0], k * PANEL_W : k * PANEL_W + p.shape[1]] = p
    write_atomic(d / REPORT_PNG, _png(png, REPORT_PNG))

    e = html.escape
    b, g, r = _COLOURS.get(verdict.verdict, (80, 80, 80))
    colour = f"#{r:02x}{g:02x}{b:02x}"
    parts = [
        "<!DOCTYPE html><html><head><meta charset='utf-8'>",
        f"<title>slidecal {e(verdict.command)}: {e(verdict.verdict)}</title>",
        "<style>body{font-family:sans-serif;margin:20px;max-width:1200px}"
        "table{border-collapse:collapse}td,th{border:1px solid #bbb;padding:3px 8px;"
        "font-size:13px}.fail{background:#fdd}.pass{background:#efe}"
        f".banner{{background:{colour};color:#fff;padding:10px 16px;font-size:24px}}"
        "img{max-width:100%;border:1px solid #ccc}</style></head><body>",
        f"<div class='banner'>{e(verdict.command)}: {e(verdict.verdict.upper())}</div>",
        f"<p>Session: {e(str(d.resolve()))}; {len(problem.frames)} frames.</p>",
    ]
    if verdict.reasons:
        parts.append("<h2>Reasons</h2><ul>")
        parts += [f"<li>{e(c.message)}</li>" for c in verdict.reasons]
        parts.append("</ul>")
    if summary:  # the calibration's values near the top
        parts.append(f"<h2>The calibration</h2><pre>{e(summary)}</pre>")
    parts.append(
        "<h2>Every test</h2><table><tr><th>test</th><th>result</th><th>figure</th>"
        "<th>limit</th><th>what</th></tr>"
    )
    for c in verdict.checks:
        cls = "pass" if c.passed else "fail"
        val = "" if c.value is None else f"{c.value:.4g}"
        lim = "" if c.limit is None else f"{c.limit:.4g}"
        parts.append(
            f"<tr class='{cls}'><td>{e(c.test)}</td><td>{'pass' if c.passed else 'FAIL'}</td>"
            f"<td>{val}</td><td>{lim}</td><td>{e(c.message)}</td></tr>"
        )
    parts.append("</table>")
    if verdict.installed is not None:
        parts.append(
            "<h2>Against the installed calibration</h2><table>"
            "<tr><th>quantity</th><th>change (combined sigma)</th></tr>"
        )
        for k, v in (verdict.installed.get("sigma") or {}).items():
            parts.append(f"<tr><td>{e(k)}</td><td>{'' if v is None else f'{v:.2f}'}</td></tr>")
        for k, v in (verdict.installed.get("max_displacement_px") or {}).items():
            parts.append(
                f"<tr><td>{e(k)}: displacement at the working distance (px)</td>"
                f"<td>{'' if v is None else f'{v:.3f}'}</td></tr>"
            )
        parts.append("</table>")
    elif installed is None:
        parts.append("<p>No installed calibration to compare with.</p>")
    for title, img in panels:
        b64 = base64.b64encode(_png(img)).decode()
        parts.append(f"<h2>{e(title)}</h2><img alt='{e(title)}' src='data:image/png;base64,{b64}'>")
    if verdict.notes:
        parts.append(
            "<h2>Notes</h2><ul>" + "".join(f"<li>{e(n)}</li>" for n in verdict.notes) + "</ul>"
        )
    parts.append("</body></html>")
    path = d / REPORT_HTML
    write_atomic(path, "\n".join(parts))
    return path

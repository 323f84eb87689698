"""The detector's floor: a free board pose fitted to every image, with fixed intrinsics (the
detector's and the lens model's noise, measured without the robot model)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slidecal.solver.camera import opencv_view, project, project_with_jacobians
from slidecal.solver.geometry import R_from_rvecs, T_from_Rt
from slidecal.solver.model import BundleModel, ModelState


@dataclass(frozen=True)
class FreePoseFit:
    """Per image ``(frame index, camera)``: residual sum of squares (pixels^2), rows used and
    the fitted ``T_cam_board``; ``sigma_px`` per camera: ``sqrt(sum rss / sum(rows - 6))``."""

    rss: dict[tuple[int, str], float]
    rows: dict[tuple[int, str], int]
    T_cam_board: dict[tuple[int, str], np.ndarray]
    sigma_px: dict[str, float]


def free_pose_fit(
    images: list[tuple[int, str, np.ndarray, np.ndarray]],
    K: dict[str, np.ndarray],
    dist: dict[str, np.ndarray],
    starts: dict[tuple[int, str], np.ndarray] | None = None,
    closed_form: bool = True,
) -> FreePoseFit:
    """Fit a free board pose to every image with fixed intrinsics and distortion.

    ``images``: (frame index, camera, board points (n, 3), pixels (n, 2)) of the inlier
    detections. Each pose is the reprojection error's minimum from the better of ``starts``
    (``T_cam_board`` per (frame index, camera)) and the closed-form planar solution (IPPE), so
    that a wrong robot model cannot spoil the floor it is judged against; images with fewer
    than 4 points are skipped. ``closed_form`` False: IPPE only for the images without a start.
    """
    todo = [
        (fi, cam, np.asarray(pts, np.float64), np.asarray(px, np.float64))
        for fi, cam, pts, px in images
        if len(pts) >= 4
    ]
    starts = starts or {}
    refined = _refined(todo, [starts.get((fi, cam)) for fi, cam, _, _ in todo], K, dist)
    closed: list[np.ndarray | None] = []
    for (_, cam, obj, img), T in zip(todo, refined, strict=True):
        if T is not None and not closed_form:
            closed.append(None)
            continue
        Kc, dc, ic = opencv_view(K[cam], dist[cam], img)
        ok, rv, tv = cv2.solvePnP(obj, ic, Kc, dc, flags=cv2.SOLVEPNP_IPPE)
        closed.append(T_from_Rt(cv2.Rodrigues(rv)[0], tv.reshape(3)) if ok else None)
    best = _scored(todo, refined, K, dist)
    closed_rss = _scored(todo, closed, K, dist)
    # the closed form is refined only when it beats the refined model start (a wrong robot
    # model starting the pose in the wrong basin)
    beats = [c is not None and (b is None or c < b) for b, c in zip(best, closed_rss, strict=True)]
    alt = _refined(todo, [T if b else None for T, b in zip(closed, beats, strict=True)], K, dist)
    alt_rss = _scored(todo, alt, K, dist)
    rss: dict[tuple[int, str], float] = {}
    rows: dict[tuple[int, str], int] = {}
    poses: dict[tuple[int, str], np.ndarray] = {}
    sums: dict[str, list[float]] = {}
    for k, (fi, cam, obj, _) in enumerate(todo):
        T, e = refined[k], best[k]
        if alt_rss[k] is not None and (e is None or alt_rss[k] < e):
            T, e = alt[k], alt_rss[k]
        if e is None:
            continue
        key = (fi, cam)
        rss[key], rows[key], poses[key] = e, 2 * len(obj), T
        acc = sums.setdefault(cam, [0.0, 0])
        acc[0] += e
        acc[1] += 2 * len(obj) - 6
    sigma = {c: float(np.sqrt(t / d)) if d > 0 else float("nan") for c, (t, d) in sums.items()}
    return FreePoseFit(rss, rows, poses, sigma)


def _refined(
    todo: list[tuple[int, str, np.ndarray, np.ndarray]],
    starts: list[np.ndarray | None],
    K: dict[str, np.ndarray],
    dist: dict[str, np.ndarray],
) -> list[np.ndarray | None]:
    """Per image of ``todo``: ``T_cam_board`` refined from its start in ``starts`` (None: no
    start, or the board behind the camera) by :func:`_pose_minima`, a camera's images at once."""
    out: list[np.ndarray | None] = [None] * len(todo)
    for cam in dict.fromkeys(c for _, c, _, _ in todo):
        sel = [
            k
            for k, (_, c, _, _) in enumerate(todo)
            if c == cam and starts[k] is not None and starts[k][2, 3] > 0
        ]
        if not sel:
            continue
        m, n = len(sel), max(len(todo[k][2]) for k in sel)
        obj, img, w = np.zeros((m, n, 3)), np.zeros((m, n, 2)), np.zeros((m, n, 1))
        for i, k in enumerate(sel):
            nk = len(todo[k][2])
            obj[i], img[i], w[i, :nk] = todo[k][2][0], todo[k][3][0], 1.0
            obj[i, :nk], img[i, :nk] = todo[k][2], todo[k][3]
        T = _pose_minima(K[cam], dist[cam], obj, img, w, np.stack([starts[k] for k in sel]))
        for i, k in enumerate(sel):
            out[k] = T[i]
    return out


def _pose_minima(
    K: np.ndarray,
    dist: np.ndarray,
    obj: np.ndarray,
    img: np.ndarray,
    w: np.ndarray,
    T: np.ndarray,
    max_iter: int = 20,
) -> np.ndarray:
    """The poses ``T`` (m, 4, 4) at their images' reprojection minima (OpenCV's iterative
    PnP, for m images at once): board points ``obj`` (m, n, 3), pixels ``img`` (m, n, 2),
    weights ``w`` (m, n, 1, 0 for padding). Levenberg-Marquardt, the rotation stepped on the
    left; an image stops where its squares stop falling by 1e-10 of themselves."""
    m, n = w.shape[:2]
    T = T.copy()

    def errors(k: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple:
        """Images ``k``'s weighed residuals (k, 2 n, 1), squares and Jacobian (k, 2 n, 6)."""
        q = obj[k] @ np.swapaxes(R, 1, 2)  # the board points rotated into the camera
        pr = project_with_jacobians(K, dist, (q + t[:, None]).reshape(-1, 3), params=False)
        e = (pr.px.reshape(len(k), n, 2) - img[k]) * w[k]
        D = pr.d_P.reshape(len(k), n, 2, 3) * w[k][:, :, :, None]
        J = np.concatenate([np.cross(q[:, :, None], D), D], axis=3).reshape(len(k), 2 * n, 6)
        return e.reshape(len(k), 2 * n, 1), np.sum(e * e, axis=(1, 2)), J

    k, lam = np.arange(m), np.full(m, 1e-6)  # the images still moving, their damping
    e, cost, J = errors(k, T[:, :3, :3], T[:, :3, 3])
    for _ in range(max_iter):
        Jt = np.swapaxes(J, 1, 2)
        H = Jt @ J
        H += lam[:, None, None] * np.diagonal(H, axis1=1, axis2=2)[:, :, None] * np.eye(6)
        step = -np.linalg.solve(H, Jt @ e)[:, :, 0]
        R, t = R_from_rvecs(step[:, :3]) @ T[k, :3, :3], T[k, :3, 3] + step[:, 3:]
        e_new, cost_new, J_new = errors(k, R, t)
        ok = cost_new <= cost  # a nan is no decrease
        T[k[ok], :3, :3], T[k[ok], :3, 3] = R[ok], t[ok]
        e[ok], J[ok], lam = e_new[ok], J_new[ok], np.where(ok, lam / 10.0, lam * 10.0)
        go = (np.abs(cost - cost_new) > 1e-10 * cost) & (lam < 1e6)  # else converged, or stuck
        cost = np.where(ok, cost_new, cost)
        k, e, cost, J, lam = k[go], e[go], cost[go], J[go], lam[go]
        if not len(k):
            break
    return T


def _scored(
    todo: list[tuple[int, str, np.ndarray, np.ndarray]],
    poses: list[np.ndarray | None],
    K: dict[str, np.ndarray],
    dist: dict[str, np.ndarray],
) -> list[float | None]:
    """Per image of ``todo`` (frame index, camera, board points, pixels): the residual sum of
    squares (pixels^2) of its board pose ``T_cam_board`` in ``poses``; None without a pose or
    with the board behind the camera. One projection per camera for all its images."""
    out: list[float | None] = [None] * len(todo)
    for cam in dict.fromkeys(c for _, c, _, _ in todo):
        sel = [k for k, (_, c, _, _) in enumerate(todo) if c == cam and poses[k] is not None]
        if not sel:
            continue
        n = np.array([len(todo[k][2]) for k in sel])
        T = np.repeat(np.stack([poses[k] for k in sel]), n, axis=0)  # each point's pose
        obj = np.concatenate([todo[k][2] for k in sel])
        P = np.einsum("nij,nj->ni", T[:, :3, :3], obj) + T[:, :3, 3]
        e = project(K[cam], dist[cam], P) - np.concatenate([todo[k][3] for k in sel])
        first = np.concatenate([[0], np.cumsum(n)[:-1]])
        rss = np.add.reduceat(np.sum(e * e, axis=1), first)
        front = np.minimum.reduceat(P[:, 2], first) > 0
        for k, r, f in zip(sel, rss, front, strict=True):
            if f:
                out[k] = float(r)
    return out


def pnp_from(
    obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist: np.ndarray, T0: np.ndarray
) -> np.ndarray | None:
    """OpenCV's iterative PnP (the reprojection-error minimum) started at ``T0``: the pose
    ``T_cam_board``, or None when it fails."""
    rv0 = cv2.Rodrigues(T0[:3, :3])[0]
    K, dist, img = opencv_view(K, dist, img)
    ok, rv, tv = cv2.solvePnP(
        obj, img, K, dist, rv0, T0[:3, 3].reshape(3, 1).copy(), True, cv2.SOLVEPNP_ITERATIVE
    )
    if not ok:
        return None
    return T_from_Rt(cv2.Rodrigues(rv)[0], tv.reshape(3))


def session_images(
    model: BundleModel, inlier_rows: np.ndarray
) -> list[tuple[int, str, np.ndarray, np.ndarray]]:
    """The inlier detections (``inlier_rows`` (R,) bool, a solve's) of ``model`` as
    ``free_pose_fit`` takes them."""
    images = []
    for ch in model.chunks:
        keep = inlier_rows[ch.rows][0::2]
        images.append((ch.frame_index, ch.camera, ch.points[keep], ch.px[keep]))
    return images


def model_starts(m: BundleModel, state: ModelState) -> dict[tuple[int, str], np.ndarray]:
    """``T_cam_board`` per (frame index, camera) as the model ``m`` predicts it at ``state``."""
    starts = {}
    for ch in m.chunks:
        T = m.T_ref_board(state, ch.frame_index)
        if ch.camera != m.ref:
            T = state.T_cam_ref[ch.camera] @ T
        starts[(ch.frame_index, ch.camera)] = T
    return starts

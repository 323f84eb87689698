"""The detector's floor: a free board pose fitted to every image, with fixed intrinsics.

The residual of that fit is the detector's and the lens model's noise measured without the robot
model: the optimiser's test of the robot poses (:func:`slidecal.solver.refine.refine`) and the
adequacy checks (:mod:`slidecal.solver.adequacy`) both compare a solve against it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from slidecal.solver.camera import opencv_view, project
from slidecal.solver.geometry import T_from_Rt
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
    detections. Each pose is OpenCV's iterative PnP minimum from the better of ``starts``
    (``T_cam_board`` per (frame index, camera)) and the closed-form planar solution (IPPE), so
    that a wrong robot model cannot spoil the floor it is judged against; images with fewer
    than 4 points are skipped. ``closed_form`` False: IPPE only for the images without a start
    or whose start does not refine.
    """
    todo = [
        (fi, cam, pts.astype(np.float64), px.astype(np.float64))
        for fi, cam, pts, px in images
        if len(pts) >= 4
    ]
    starts = starts or {}
    refined: list[np.ndarray | None] = []
    closed: list[np.ndarray | None] = []
    for fi, cam, obj, img in todo:
        T0 = starts.get((fi, cam))
        good_start = T0 is not None and T0[2, 3] > 0
        refined.append(pnp_from(obj, img, K[cam], dist[cam], T0) if good_start else None)
        if good_start and not closed_form and refined[-1] is not None:
            closed.append(None)
            continue
        Kc, dc, ic = opencv_view(K[cam], dist[cam], img)
        ok, rv, tv = cv2.solvePnP(obj, ic, Kc, dc, flags=cv2.SOLVEPNP_IPPE)
        closed.append(T_from_Rt(cv2.Rodrigues(rv)[0], tv.reshape(3)) if ok else None)
    best = _scored(todo, refined, K, dist)
    closed_rss = _scored(todo, closed, K, dist)
    # the closed form is refined only when it beats the refined model start (a wrong robot
    # model starting the pose in the wrong basin)
    alt: list[np.ndarray | None] = [None] * len(todo)
    for k, (_, cam, obj, img) in enumerate(todo):
        if closed_rss[k] is not None and (best[k] is None or closed_rss[k] < best[k]):
            alt[k] = pnp_from(obj, img, K[cam], dist[cam], closed[k])
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

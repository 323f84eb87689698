"""The paired drift test: the same commanded robot poses, seen twice, compared corner by corner
by the displacement field ``d = s + a q + w J q`` per shared pose, averaged over the poses, as
docs/UNATTENDED.md ("The paired comparison") states it; ``z``: each mean over its one-sigma.
Drift: the largest ``z`` beyond :data:`Z_LIMIT` AND the field's largest displacement beyond
the pixel limit.

The unpaired check (:func:`fit_target`, :func:`chain_rms_px`): the installed calibration held
fixed, the one target pose that best explains new images through the measured robot poses, and
the residuals it leaves per camera. Arrays in, :class:`DisplacementField` out; no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from slidecal.solver.camera import opencv_view, project
from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T, rvec_from_R
from slidecal.solver.numeric import least_squares, median
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.result import CalibrationResult

#: A field is significant beyond this many one-sigmas.
Z_LIMIT = 5.0
#: Fewest shared poses for the test (the pose-to-pose scatter is estimated from them).
MIN_POSES = 3
#: Fewest common corners of a pose.
MIN_CORNERS = 8
#: A pose whose corners moved by more than this (median, px) does not match: the board or
#: the camera moved far beyond a drift (the paired comparison is not usable there).
GROSS_PX = 20.0
#: Matching two measured robot poses as the same commanded pose: position and rotation.
MATCH_M = 1e-3
MATCH_DEG = 0.1


@dataclass(frozen=True)
class DisplacementField:
    """The paired comparison of one camera (see the module docstring).

    ``mean_px`` (4,): shift x, shift y, scale, rotation (px, scale and rotation at
    ``radius_px``); ``std_px`` (4,) their one-sigma; ``z`` (4,) = |mean| / std.
    ``max_px``: the largest displacement of the mean field over the region compared.
    ``corner_noise_px``: the per-corner scatter (robust, per axis) about the poses' fields.
    ``pose_scatter_px``: the rms scatter of the per-pose shifts about their mean (per axis).
    ``equivalent``: what the field corresponds to through the installed intrinsics:
    ``cx_px``, ``cy_px`` (the shift as a principal-point change), ``rx_deg``, ``ry_deg`` (the
    shift as a camera rotation about its x, y axes), ``f_rel`` (the scale as a relative
    focal-length change), ``rz_deg`` (the rotation as one about the optical axis) and
    ``rotation_deg`` (the shift and rotation as one camera rotation).
    """

    n_poses: int
    n_corners: int
    radius_px: float
    mean_px: np.ndarray
    std_px: np.ndarray
    z: np.ndarray
    max_px: float
    corner_noise_px: float
    pose_scatter_px: float
    equivalent: dict[str, float]

    @property
    def max_z(self) -> float:
        """The largest ``z`` of the four parameters."""
        return float(np.max(self.z))

    def drifted(self, px_limit: float) -> bool:
        """Significant and larger than ``px_limit``."""
        return self.max_z > Z_LIMIT and self.max_px > px_limit


def match_poses(
    new: Sequence[np.ndarray | None],
    old: Sequence[np.ndarray | None],
) -> list[tuple[int, int]]:
    """Pairs ``(i, j)``: pose ``new[i]`` is ``old[j]`` (``T_base_tool`` (4, 4) both, within
    ``MATCH_M`` and ``MATCH_DEG``; the nearest when several are); None poses never match."""
    ia = [i for i, T in enumerate(new) if T is not None]
    jb = [j for j, T in enumerate(old) if T is not None]
    if not ia or not jb:
        return []
    A = np.array([new[i] for i in ia], dtype=float)
    B = np.array([old[j] for j in jb], dtype=float)
    dt = np.linalg.norm(A[:, None, :3, 3] - B[None, :, :3, 3], axis=2)
    cos = (np.einsum("iab,jab->ij", A[:, :3, :3], B[:, :3, :3]) - 1.0) / 2.0
    dr = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    cost = np.where((dt <= MATCH_M) & (dr <= MATCH_DEG), dt / MATCH_M + dr / MATCH_DEG, np.inf)
    best = np.argmin(cost, axis=1)
    return [(ia[k], jb[int(best[k])]) for k in range(len(ia)) if np.isfinite(cost[k, best[k]])]


def common_corners(
    ids_new: np.ndarray, px_new: np.ndarray, ids_old: np.ndarray, px_old: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The pixels (n, 2) old and new of the corners both detections hold, by id."""
    ids_new = np.asarray(ids_new).reshape(-1)
    ids_old = np.asarray(ids_old).reshape(-1)
    _, a, b = np.intersect1d(ids_old, ids_new, assume_unique=False, return_indices=True)
    return np.asarray(px_old, float).reshape(-1, 2)[a], np.asarray(px_new, float).reshape(-1, 2)[b]


def _design(q: np.ndarray) -> np.ndarray:
    n = len(q)
    A = np.zeros((2 * n, 4))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[0::2, 2], A[1::2, 2] = q[:, 0], q[:, 1]
    A[0::2, 3], A[1::2, 3] = -q[:, 1], q[:, 0]
    return A


def _robust_sigma(r: np.ndarray) -> float:
    return float(1.4826 * median(np.abs(r - median(r)))) if len(r) else 0.0


def displacement_field(
    old_px: Sequence[np.ndarray],
    new_px: Sequence[np.ndarray],
    K: np.ndarray,
    region: tuple[float, float, float, float],
) -> DisplacementField:
    """The paired test of one camera: ``old_px[k]``, ``new_px[k]`` (n_k, 2) the same corners
    at shared pose ``k``; ``K`` (3, 3) the installed intrinsics; ``region`` (u0, v0, u1, v1)
    the image box over which the largest displacement of the field is taken. Raises
    :class:`DegenerateError` with fewer than :data:`MIN_POSES` poses of at least
    :data:`MIN_CORNERS` corners."""
    K = np.asarray(K, dtype=float)
    c = K[:2, 2]
    poses = [
        (np.asarray(a, float).reshape(-1, 2), np.asarray(b, float).reshape(-1, 2))
        for a, b in zip(old_px, new_px, strict=True)
        if len(a) >= MIN_CORNERS
    ]
    if len(poses) < MIN_POSES:
        raise DegenerateError(
            f"{len(poses)} shared poses with {MIN_CORNERS}+ common corners; the paired test "
            f"needs {MIN_POSES}"
        )
    all_old = np.vstack([a for a, _ in poses])
    R = float(np.sqrt(np.mean(np.sum((all_old - c) ** 2, axis=1))))
    R = R if R > 1.0 else 1.0
    fits, resid, designs = [], [], []
    for a, b in poses:
        A = _design((a - c) / R)
        d = (b - a).reshape(-1)
        keep = np.ones(len(d), dtype=bool)
        for _ in range(2):  # fit, drop corners beyond five robust sigmas, refit
            theta = np.linalg.lstsq(A[keep], d[keep], rcond=None)[0]
            r = d - A @ theta
            s = max(_robust_sigma(r[keep]), 1e-6)
            pair = np.repeat(np.abs(r).reshape(-1, 2).max(axis=1) <= 5.0 * s, 2)
            if pair.sum() < 2 * MIN_CORNERS or np.array_equal(pair, keep):
                break
            keep = pair
        fits.append(theta)
        resid.append(r[keep])
        designs.append(A[keep])
    theta = np.array(fits)
    n = len(theta)
    mean = theta.mean(axis=0)
    sigma_c = _robust_sigma(np.concatenate(resid))
    within = (
        np.mean([np.diag(np.linalg.pinv(A.T @ A)) for A in designs], axis=0) * sigma_c**2
    )  # one pose's variance from the corners' scatter alone
    dev = theta - mean
    var = np.empty(4)
    for grp in ((0, 1), (2, 3)):  # pooled: the shifts, and scale with rotation
        var[list(grp)] = float(np.sum(dev[:, grp] ** 2)) / (len(grp) * (n - 1))
    var = np.maximum(var, within)
    std = np.sqrt(var / n)
    z = np.abs(mean) / np.where(std > 0, std, np.inf)
    u0, v0, u1, v1 = region
    box = np.array([[u0, v0], [u1, v0], [u0, v1], [u1, v1]], dtype=float)
    field = _design((box - c) / R) @ mean
    max_px = float(np.max(np.linalg.norm(field.reshape(-1, 2), axis=1)))
    fx, fy = K[0, 0], K[1, 1]
    rx, ry, rz = mean[1] / fy, -mean[0] / fx, -mean[3] / R
    equivalent = {
        "cx_px": float(mean[0]),
        "cy_px": float(mean[1]),
        "rx_deg": float(np.degrees(rx)),
        "ry_deg": float(np.degrees(ry)),
        "f_rel": float(mean[2] / R),
        "rz_deg": float(np.degrees(rz)),
        "rotation_deg": float(np.degrees(np.sqrt(rx**2 + ry**2 + rz**2))),
    }
    return DisplacementField(
        n_poses=n,
        n_corners=int(sum(len(a) for a, _ in poses)),
        radius_px=R,
        mean_px=mean,
        std_px=std,
        z=z,
        max_px=max_px,
        corner_noise_px=sigma_c,
        pose_scatter_px=float(np.sqrt(np.mean(dev[:, :2] ** 2))) if n > 1 else 0.0,
        equivalent=equivalent,
    )


# -- the installed calibration against new images, unpaired ------------------------------------
def hand_eye_T(installed: CalibrationResult, camera: str) -> np.ndarray:
    """``T_tool_<camera>`` (eye-in-hand) or ``T_base_<camera>`` (eye-to-hand) (4, 4) of the
    installed calibration: its hand-eye for the reference camera, composed with the rig's
    ``T_<camera>_<reference>`` for the others; InputError unless rotation and translation are
    both known."""
    he = installed.hand_eye
    T = None
    if he is not None:
        ref = installed.reference_camera or next(iter(installed.cameras))
        if camera == ref:
            T = he.T
        elif (rig := installed.rig.get(f"T_{camera}_{ref}")) is not None:
            # T_tool_cam = T_tool_ref @ T_ref_cam = T_tool_ref @ inv(T_cam_ref)
            known = (he.R, rig.R, he.t_m, rig.t_m)
            if all(v is not None for v in known):
                T = T_from_Rt(he.R @ rig.R.T, he.R @ (-rig.R.T @ rig.t_m) + he.t_m)
    if T is None:
        raise InputError(
            f"the installed calibration has no complete hand-eye for camera {camera!r}; "
            "check needs the hand-eye rotation and translation"
        )
    return T


def T_cam_board(mount: str, X: np.ndarray, T_base_tool: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """``T_cam_board`` (4, 4) from the hand-eye ``X`` (T_tool_cam or T_base_cam), the robot pose
    and the target pose ``Y`` (T_base_board or T_tool_board)."""
    if mount == "eye_in_hand":
        return inv_T(X) @ inv_T(T_base_tool) @ Y
    return inv_T(X) @ T_base_tool @ Y


def fit_target(
    problem: CalibrationProblem, installed: CalibrationResult
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The target pose (4, 4) that best explains the images with the installed calibration
    held fixed, and the residual vectors (N, 2) px per camera."""
    mount = installed.mount
    cams = [c.name for c in problem.cameras if c.name in installed.cameras]
    X = {c: hand_eye_T(installed, c) for c in cams}
    pts = problem.target.points_m
    obs = []
    for fr in problem.frames:
        if fr.T_base_tool is None:
            continue
        for c in cams:
            det = fr.detections.get(c)
            if det is not None and len(det.ids) >= 4:
                obs.append((c, fr.T_base_tool, pts[det.ids], np.asarray(det.px, float)))
    if not obs:
        raise InputError("no frame of the check saw the target; check the cell and the board")
    Y0 = installed.T_target.T if installed.T_target is not None else None
    if Y0 is None:
        c, T, P, px = obs[0]
        cam = installed.cameras[c]
        K, d, seen = opencv_view(np.asarray(cam.K, float), cam.distortion, px)  # any lens
        ok, rv, tv = cv2.solvePnP(P.astype(np.float64), seen, K, d)
        T_cb = T_from_Rt(cv2.Rodrigues(rv)[0], tv.ravel())
        Y0 = T @ X[c] @ T_cb if mount == "eye_in_hand" else inv_T(T) @ X[c] @ T_cb

    def residuals(theta: np.ndarray) -> np.ndarray:
        Y = T_from_Rt(R_from_rvec(theta[:3]), theta[3:])
        out = []
        for c, T, P, px in obs:
            cam = installed.cameras[c]
            Tcb = T_cam_board(mount, X[c], T, Y)
            Pc = P @ Tcb[:3, :3].T + Tcb[:3, 3]
            out.append((project(np.asarray(cam.K), np.asarray(cam.distortion), Pc) - px).ravel())
        return np.concatenate(out)

    theta0 = np.concatenate([rvec_from_R(Y0[:3, :3]), Y0[:3, 3]])
    sol = least_squares(residuals, theta0)
    Y = T_from_Rt(R_from_rvec(sol.x[:3]), sol.x[3:])
    r = residuals(sol.x).reshape(-1, 2)
    of = np.repeat([c for c, *_ in obs], [len(P) for _, _, P, _ in obs])  # each row's camera
    return Y, {c: r[of == c] for c in cams}


def chain_rms_px(result: CalibrationResult, problem: CalibrationProblem) -> dict[str, float]:
    """Per camera, the rms (norm) of the residuals of ``result`` on its own session with the
    robot poses as measured (what :func:`fit_target` sees on an unchanged cell)."""
    out = {}
    try:
        _, res = fit_target(problem, result)
    except InputError:
        return out
    for n, r in res.items():
        if len(r):
            out[n] = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
    return out

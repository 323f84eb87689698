"""The lens model the images ask for: the screen, the free-pose fits and the test of
docs/ERROR_MODEL.md Sec. 5 ("The lens model")."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import cv2
import numpy as np

from slidecal.solver.camera import DISTORTION_MODELS, project, project_with_jacobians
from slidecal.solver.geometry import T_from_Rt
from slidecal.solver.model import orientation_groups
from slidecal.solver.numeric import chi2_tail, distinct
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.result import CalibrationResult

#: False-alarm rate of the lens test for a nested richer model and independent corner errors
LENS_TEST_P = 1e-3
#: Images per camera the test fits at most (evenly spread): enough to tell lens models apart,
#: and a bound on its time
LENS_TEST_IMAGES = 40
#: The noise the test assumes at least (px per coordinate): a tenth of a sharp image's detector
#: noise, so that exact simulated corners do not make round-off a lens
LENS_NOISE_FLOOR_PX = 0.01
#: The screen's false-alarm rate: ten times the test's, a margin for its linearisation (a
#: camera goes on only when the fits then beat it at LENS_TEST_P too)
LENS_SCREEN_P = 1e-2
_MIN_IMAGES, _MIN_CORNERS = 4, 6  # a free-pose fit of a planar target needs them


def _free_fit(
    obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int], model: str, mask
) -> tuple[float, int] | None:
    """Sum of squared residuals (px^2, by :func:`project`) and parameters of OpenCV's free-pose
    calibration with lens ``model`` and its coefficients ``mask``; None when it fails."""
    names = DISTORTION_MODELS[model]
    fisheye = model == "fisheye"
    flags = 0
    for n, on in zip(names, mask, strict=True):  # hold the coefficient at 0 (p1, p2 together)
        fix = "ZERO_TANGENT_DIST" if n[0] == "p" else f"FIX_{n.upper()}"
        flags |= 0 if on else getattr(cv2.fisheye if fisheye else cv2, f"CALIB_{fix}")
    try:
        if fisheye:
            flags |= cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
            crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 30, 1e-8)  # it settles in 30
            o = [p.reshape(-1, 1, 3) for p in obj]
            _, K, d, rv, tv = cv2.fisheye.calibrate(
                o, img, size, None, None, flags=flags, criteria=crit
            )
        else:
            flags |= cv2.CALIB_RATIONAL_MODEL if model == "rational" else 0
            _, K, d, rv, tv = cv2.calibrateCamera(obj, img, size, None, None, flags=flags)
    except cv2.error:
        return None
    d = np.asarray(d, float).ravel()[: len(names)]
    cost = 0.0
    for p, q, r, t in zip(obj, img, rv, tv, strict=True):
        T = T_from_Rt(cv2.Rodrigues(np.asarray(r, float))[0], np.asarray(t, float).ravel())
        e = project(K, d, p @ T[:3, :3].T + T[:3, 3]) - q.reshape(-1, 2)
        cost += float(np.sum(e * e))
    return (cost, 4 + int(sum(mask)) + 6 * len(obj)) if np.isfinite(cost) else None


def _screen_fits(
    obj: list[np.ndarray], img: list[np.ndarray], K: np.ndarray, dist: np.ndarray, mask
) -> dict[str, tuple[float, int]]:
    """The free-pose fits of :func:`_free_fit` of opencv5 with coefficients ``mask`` and of the
    rational model, linearised: each image's pose from OpenCV's planar PnP at ``K``, ``dist``
    (opencv5), then one Gauss-Newton step of the poses, fx, fy, cx, cy and the coefficients."""
    P, n = [], [len(p) for p in obj]
    obj, img = [p.astype(float) for p in obj], [q.astype(float) for q in img]
    for p, q in zip(obj, img, strict=True):
        _, rv, tv = cv2.solvePnP(p, q, K, dist, flags=cv2.SOLVEPNP_IPPE)
        P.append(p @ cv2.Rodrigues(rv)[0].T + tv.ravel())
    P = np.concatenate(P)
    pr = project_with_jacobians(K, np.r_[dist, 0.0, 0.0, 0.0], P)  # rational, k4-k6 at 0
    r = np.concatenate(img).reshape(-1, 2, 1) - pr.px[:, :, None]
    J_pose = np.concatenate([np.cross(P[:, None], pr.d_P), pr.d_P], axis=2)  # rotation, shift
    J = np.concatenate([pr.d_K[:, :, :4], pr.d_dist, r], axis=2)
    first = np.r_[0, np.cumsum(n)[:-1]]
    A = np.add.reduceat(np.einsum("nki,nkj->nij", J_pose, J_pose), first)
    B = np.add.reduceat(np.einsum("nki,nkj->nij", J_pose, J), first)
    J = (J - J_pose @ np.repeat(np.linalg.solve(A, B), n, axis=0)).reshape(-1, J.shape[2])
    J, r = J[:, :-1] / np.linalg.norm(J[:, :-1], axis=0), J[:, -1]  # the poses eliminated
    fits = {}
    for m, cols in (("opencv5", np.r_[0:4, 4 + np.flatnonzero(mask)]), ("rational", range(12))):
        e = r - J[:, cols] @ np.linalg.lstsq(J[:, cols], r, rcond=None)[0]
        fits[m] = (float(e @ e), len(cols) + 6 * len(obj))
    return fits


def _beats(fits: dict, n_rows: int, a: str, b: str, level: float = LENS_TEST_P) -> float | None:
    """How far model ``a``'s free-pose fit lowers model ``b``'s squares, in units of ``a``'s own
    noise variance; None when not beyond chance (tail ``level``) on ``a``'s extra coefficients
    (at least one)."""
    if fits.get(a) is None or fits.get(b) is None:
        return None
    (c, p), (c_b, p_b) = fits[a], fits[b]
    d = (c_b - c) / max(c / (n_rows - p), LENS_NOISE_FLOOR_PX**2)
    return d if d > 0 and chi2_tail(max(p - p_b, 1), d) < level else None


def lens_check(
    problem: CalibrationProblem, result: CalibrationResult | None = None
) -> tuple[str, str] | None:
    """(the lens model the images ask for, why, one line) when one camera's images ask for
    another than ``problem.options.lens``: of the models that beat it, the one with the fewest
    coefficients that no other beats. None when none does or the test cannot run. ``result``:
    the solve of ``problem``, whose opencv5 cameras are screened first."""
    o = problem.options
    if problem.knowledge not in ("robot", "none"):
        return None
    if problem.knowledge == "robot":
        T = np.stack([f.T_base_tool for f in problem.frames])
        if len(set(orientation_groups(T).tolist())) < 2:
            return None
    for spec in problem.cameras:
        dets = [f.detections[spec.name] for f in problem.frames if spec.name in f.detections]
        dets = [d for d in dets if len(d.ids) >= _MIN_CORNERS]
        if len(dets) < _MIN_IMAGES:
            continue
        pick = distinct(np.linspace(0, len(dets) - 1, LENS_TEST_IMAGES).round().astype(int))
        obj = [problem.target.points_m[dets[k].ids].astype(np.float32) for k in pick]
        img = [dets[k].px.reshape(-1, 1, 2).astype(np.float32) for k in pick]
        n_rows = 2 * sum(len(p) for p in obj)
        size = (spec.width, spec.height)
        cam = None if result is None else result.cameras.get(spec.name)
        if cam is not None and o.lens == "opencv5" and result.converged:
            fits = _screen_fits(obj, img, cam.K, cam.distortion, o.distortion_mask)
            if _beats(fits, n_rows, "rational", "opencv5", LENS_SCREEN_P) is None:
                continue
        fits = {}
        for m, v in DISTORTION_MODELS.items():
            # fisheye (the slowest fit) only where the five coefficients leave a richer lens
            wide = m != "fisheye" or o.lens == m or _beats(fits, n_rows, "rational", "opencv5")
            mask = o.distortion_mask if m == o.lens else (True,) * len(v)
            fits[m] = _free_fit(obj, img, size, m, mask) if wide else None
        asked = [m for m in fits if m != o.lens and _beats(fits, n_rows, m, o.lens) is not None]
        beaten = {m: any(_beats(fits, n_rows, x, m) for x in fits if x != m) for m in asked}
        asked.sort(key=lambda m: (beaten[m], fits[m][1]))
        if asked:
            m = asked[0]
            rms_used, rms = (np.sqrt(2 * fits[x][0] / n_rows) for x in (o.lens, m))
            return m, (
                f"camera {spec.name}'s images ask for the {m} lens model: fitted alone with it "
                f"their residuals fall from {rms_used:.3f} to {rms:.3f} px rms, "
                f"{_beats(fits, n_rows, m, o.lens):.0f} times the noise variance, beyond chance "
                f"(p < {LENS_TEST_P:g} on its extra coefficients; docs/ERROR_MODEL.md)"
            )
    return None


def choose_lens(
    problem: CalibrationProblem,
    result: CalibrationResult,
    solve: Callable[[CalibrationProblem], CalibrationResult],
) -> CalibrationResult:
    """``result`` of ``problem`` after the lens test (:func:`lens_check`): solved again by
    ``solve`` with the model the images ask for when the options name none, else failing the
    adequacy test with the reason (a note where the session has no adequacy test)."""
    asked = lens_check(problem, result)
    if asked is None:
        return result
    model, why = asked
    o = problem.options
    if o.distortion_model is None:
        names = DISTORTION_MODELS[model]
        opts = replace(o, distortion_model=model, distortion=(True,) * len(names))
        res = solve(replace(problem, options=opts))
        note = f"lens model {model}, chosen by the data: {why}"
        return replace(res, messages=(note, *res.messages))
    fix = f"; solve with options: {{distortion_model: {model}}}"
    ad = result.adequacy
    if ad is None:
        return replace(result, messages=(*result.messages, why + fix))
    return replace(result, adequacy=replace(ad, adequate=False, reasons=(*ad.reasons, why + fix)))

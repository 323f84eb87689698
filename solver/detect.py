"""Target detection: corner ids and pixels of a ChArUco board or a chessboard in one image.

Convention: ids and the board frame of ``solver/problem.py``; pixel (0, 0) is the centre of the
top-left pixel (OpenCV's convention for corner positions, checked against rendered images in
``tests/test_detect.py``).

ChArUco: ``cv2.aruco.CharucoDetector`` (marker corners refined to sub-pixel, missed markers
recovered with ``tryRefineMarkers``, a corner accepted with one adjacent marker), then every
chessboard corner refined again with ``cv2.cornerSubPix`` in a window sized per corner so that
it holds no marker edge: the nearest marker corner lies ``(square - marker) / 2`` from the
chessboard corner along both board axes, which under a tilt can be only a few pixels away, and
a marker edge inside the window pulls the corner by tenths of a pixel.

Chessboard: ``cv2.findChessboardCornersSB`` (exhaustive, accuracy flags; the whole board must be
visible). Its corner order is ambiguous under the board's symmetries; the rule used here:

1. the board is seen from its printed side, so its +x and +y axes keep their handedness in the
   image (``x`` cross ``y`` > 0 with v pointing down);
2. the square at the board origin, next to corner 0, is black (``mocks/render.py`` prints it
   so, as does a standard OpenCV pattern of this layout);
3. if the board is symmetric under that test (``squares_x + squares_y`` even, the outer corner
   squares are all black), corner 0 is the one that makes the board's +x axis point most to the
   right in the image. Prefer boards with one odd and one even count of squares.

Quality: a local homography check flags corners that are grossly wrong (wrong id, snapped onto
a marker corner); they are removed and listed in ``rejected_ids``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from slidecal.solver.errors import InputError
from slidecal.solver.problem import Detection, Target

# Local homography check: a corner whose position differs by more than this from the prediction
# of a homography fitted to its grid neighbours (one square away, or two or three when too few)
# is rejected. Over such a neighbourhood the R1 lens (k1 = -0.12) departs from a homography by at
# most 1.33 px (noise-free, board 0.25-0.3 m away filling the image, extrapolating to the grid's
# outer corners; tests/test_detect.py checks < 1.5 px) and detector noise adds ~0.1 px, while a
# gross error is at least a marker margin (4 mm: 5.9 px at 0.6 m with 880 px focal length) or a
# whole square (a wrong id).
OUTLIER_THRESHOLD_PX = 3.0
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 60, 1e-3)
_MAX_HALF_WINDOW_PX = 8
_MIN_HALF_WINDOW_PX = 2


@dataclass(frozen=True)
class DetectionReport:
    """What ``detect`` found in one image.

    ``detection``: ids (n,) and pixels (n, 2) (empty when nothing usable). ``ok``: usable for
    calibration. ``reasons``: why not (empty when ok). ``homography_rms_px``: rms residual of one
    homography fitted to all kept corners (non-zero with lens distortion; nan below 4 corners).
    ``coverage``: fraction of the image area inside the corners' convex hull.
    ``rejected_ids``: corners removed by the local homography check.
    """

    detection: Detection
    ok: bool
    reasons: tuple[str, ...]
    homography_rms_px: float
    coverage: float
    rejected_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def charuco_board(target: Target) -> cv2.aruco.CharucoBoard:
    """OpenCV's ``CharucoBoard`` for a ``charuco`` target (same layout and corner ids)."""
    return _charuco_board(
        target.squares_x,
        target.squares_y,
        target.square_size_m,
        target.marker_size_m,
        target.dictionary or "DICT_5X5_100",
    )


@lru_cache(maxsize=8)
def _charuco_board(
    squares_x: int, squares_y: int, square_m: float, marker_m: float, dictionary: str
) -> cv2.aruco.CharucoBoard:
    if not dictionary.startswith("DICT_") or not hasattr(cv2.aruco, dictionary):
        raise InputError(
            f"unknown ArUco dictionary {dictionary!r}; use an OpenCV name such as DICT_5X5_100"
        )
    if not 0.0 < marker_m < square_m:
        raise InputError(
            f"marker_size_m ({marker_m}) must be positive and smaller than square_size_m "
            f"({square_m})"
        )
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.CharucoBoard((squares_x, squares_y), square_m, marker_m, d)


@lru_cache(maxsize=8)
def _charuco_detector(
    squares_x: int, squares_y: int, square_m: float, marker_m: float, dictionary: str
) -> cv2.aruco.CharucoDetector:
    board = _charuco_board(squares_x, squares_y, square_m, marker_m, dictionary)
    cp = cv2.aruco.CharucoParameters()
    cp.minMarkers = 1  # a corner next to one decoded marker; wrong ids are caught afterwards
    cp.tryRefineMarkers = True
    dp = cv2.aruco.DetectorParameters()
    dp.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    dp.cornerRefinementWinSize = 4
    dp.cornerRefinementMaxIterations = 50
    dp.cornerRefinementMinAccuracy = 0.01
    return cv2.aruco.CharucoDetector(board, cp, dp)


def _grey(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        img = cv2.cvtColor(np.ascontiguousarray(img), code)
    if img.ndim != 2 or min(img.shape) < 8:
        raise InputError(f"image must be (H, W) grey or (H, W, 3) BGR, got shape {np.shape(image)}")
    if img.dtype != np.uint8:
        f = img.astype(np.float64)
        lo, hi = float(np.min(f)), float(np.max(f))
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        img = np.clip((f - lo) * scale, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


def detect(image: np.ndarray, target: Target, *, min_corners: int = 8) -> DetectionReport:
    """Find the target's corners in ``image``; never raises for an image without the target.

    Parameters
    ----------
    image
        uint8 (H, W) grey or (H, W, 3) BGR (other dtypes are rescaled to 0..255).
    target
        A ``charuco`` or ``chessboard`` target.
    min_corners
        Fewer kept corners than this make the frame unusable (``ok`` False).

    Returns
    -------
    DetectionReport
        Ids and pixels (pixel (0, 0) is the centre of the top-left pixel) and diagnostics.
    """
    grey = _grey(image)
    if target.kind == "charuco":
        ids, px, reasons = _detect_charuco(grey, target)
    elif target.kind == "chessboard":
        ids, px, reasons = _detect_chessboard(grey, target)
    else:
        raise InputError(
            f"cannot detect a target of kind {target.kind!r} in images; give its detections in "
            "the session file instead"
        )
    return _report(grey.shape, target, ids, px, list(reasons), min_corners)


def _empty() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(0, dtype=np.int64), np.zeros((0, 2))


def _detect_charuco(grey: np.ndarray, target: Target) -> tuple[np.ndarray, np.ndarray, list]:
    key = (
        target.squares_x,
        target.squares_y,
        target.square_size_m,
        target.marker_size_m,
        target.dictionary or "DICT_5X5_100",
    )
    detector = _charuco_detector(*key)
    board = _charuco_board(*key)
    ch_corners, ch_ids, m_corners, m_ids = detector.detectBoard(grey)
    if m_ids is None or len(m_ids) == 0:
        return *_empty(), [
            "no ArUco marker of the target found (board not in view, seen from "
            "its back, or too blurred/dark)"
        ]
    if ch_ids is None or len(ch_ids) == 0:
        return *_empty(), [
            f"{len(m_ids)} markers found but no ChArUco corner could be interpolated"
        ]
    ids = np.asarray(ch_ids, dtype=np.int64).reshape(-1)
    px = np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2)
    # marker corners (board frame) against their image positions, to size the refinement
    # windows (CharucoBoard.matchImagePoints takes ChArUco corners, not marker corners)
    index = {int(m): k for k, m in enumerate(np.asarray(board.getIds()).reshape(-1))}
    board_obj = board.getObjPoints()
    obj, img = [], []
    for mc, mid in zip(m_corners, np.asarray(m_ids).reshape(-1), strict=True):
        if int(mid) in index:
            obj.append(np.asarray(board_obj[index[int(mid)]], dtype=np.float64).reshape(4, 3))
            img.append(np.asarray(mc, dtype=np.float64).reshape(4, 2))
    H = _homography(np.concatenate(obj)[:, :2], np.concatenate(img)) if obj else None
    if H is not None:
        px = _refine_charuco(grey, target, ids, px, H)
    return ids, px, []


def _refine_charuco(
    grey: np.ndarray, target: Target, ids: np.ndarray, px: np.ndarray, H: np.ndarray
) -> np.ndarray:
    """``cornerSubPix`` per corner with the largest window that holds no marker edge."""
    P = target.points_m[ids, :2]
    g = 0.5 * (target.square_size_m - target.marker_size_m)
    offsets = np.array([[g, g], [g, -g], [-g, g], [-g, -g]])
    centre = _apply_h(H, P)
    dist = np.full(len(ids), np.inf)
    for o in offsets:
        q = _apply_h(H, P + o)
        dist = np.minimum(dist, np.max(np.abs(q - centre), axis=1))  # L-inf: square window
    # keep the blurred marker edge (~2 px) out of the (2 w + 1) window
    half = np.floor(dist - 2.0).astype(int)
    out = px.copy()
    for w in np.unique(half):
        sel = half == w
        if w < _MIN_HALF_WINDOW_PX:
            continue  # too close to a marker to refine reliably; keep the detector's estimate
        w = min(int(w), _MAX_HALF_WINDOW_PX)
        c = px[sel].astype(np.float32).reshape(-1, 1, 2)
        r = cv2.cornerSubPix(grey, c, (w, w), (-1, -1), _SUBPIX_CRITERIA)
        out[sel] = np.asarray(r, dtype=np.float64).reshape(-1, 2)
    return out


def _detect_chessboard(grey: np.ndarray, target: Target) -> tuple[np.ndarray, np.ndarray, list]:
    cols, rows = target.squares_x - 1, target.squares_y - 1
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCornersSB(grey, (cols, rows), flags=flags)
    if not found or corners is None:
        return *_empty(), [
            f"chessboard of {cols} x {rows} inner corners not found (the whole "
            "board must be in view, seen from its printed side)"
        ]
    grid = np.asarray(corners, dtype=np.float64).reshape(rows, cols, 2)
    grid = _orient_chessboard(grey, grid)
    if grid is None:
        return *_empty(), [
            "chessboard found but its orientation is inconsistent (seen in a "
            "mirror or from the back?)"
        ]
    ids = np.arange(rows * cols, dtype=np.int64)
    return ids, grid.reshape(-1, 2), []


def _orient_chessboard(grey: np.ndarray, grid: np.ndarray) -> np.ndarray | None:
    """Reorder a (rows, cols, 2) corner grid by the rule of the module docstring."""
    rows, cols = grid.shape[:2]
    variants = [grid, grid[::-1, ::-1], grid[::-1, :], grid[:, ::-1]]
    if rows == cols:
        t = grid.transpose(1, 0, 2)
        variants += [t, t[::-1, ::-1], t[::-1, :], t[:, ::-1]]
    keep = []
    for v in variants:
        ex, ey = v[0, 1] - v[0, 0], v[1, 0] - v[0, 0]
        if ex[0] * ey[1] - ex[1] * ey[0] <= 0.0:
            continue  # mirrored: board axes with the wrong handedness
        p0 = v[0, 0]
        dark = _sample(grey, p0 - 0.5 * ex - 0.5 * ey)  # square (0, 0): black
        light = _sample(grey, p0 + 0.5 * ex - 0.5 * ey)  # square (0, 1): white
        if dark < light:
            keep.append(v)
    if not keep:
        return None

    # rule 3: the board's +x axis (corner 0 to the last corner of row 0) most to the right
    def rightward(v: np.ndarray) -> float:
        d = v[0, -1] - v[0, 0]
        return float(d[0] / (np.linalg.norm(d) + 1e-12))

    return max(keep, key=rightward)


def _sample(grey: np.ndarray, p: np.ndarray) -> float:
    """Mean grey level of a 3x3 patch around pixel ``p`` (clamped to the image)."""
    h, w = grey.shape
    u = int(np.clip(round(p[0]), 1, w - 2))
    v = int(np.clip(round(p[1]), 1, h - 2))
    return float(grey[v - 1 : v + 2, u - 1 : u + 2].mean())


def _apply_h(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    q = np.column_stack([xy, np.ones(len(xy))]) @ H.T
    return q[:, :2] / q[:, 2:3]


def _homography(xy: np.ndarray, px: np.ndarray) -> np.ndarray | None:
    """Least-squares homography board (X, Y) -> pixels, or None when degenerate."""
    if len(xy) < 4:
        return None
    c = xy - xy.mean(axis=0)
    if np.linalg.svd(c, compute_uv=False)[-1] < 1e-9 * max(1.0, np.abs(c).max()):
        return None  # collinear board points
    H, _ = cv2.findHomography(xy, px, 0)
    if H is None or not np.all(np.isfinite(H)):
        return None
    return H


def _local_residuals(ids: np.ndarray, px: np.ndarray, target: Target) -> np.ndarray:
    """Per corner: distance (px) to the prediction of a homography on its grid neighbours."""
    cols = target.squares_x - 1
    r, c = np.divmod(ids, cols)
    xy = target.points_m[ids, :2]
    res = np.zeros(len(ids))
    for i in range(len(ids)):
        for radius in (1, 2, 3):
            nb = (np.abs(r - r[i]) <= radius) & (np.abs(c - c[i]) <= radius)
            nb[i] = False
            if nb.sum() >= 6:
                H = _homography(xy[nb], px[nb])
                if H is not None:
                    res[i] = float(np.linalg.norm(_apply_h(H, xy[i : i + 1])[0] - px[i]))
                    break
    return res


def _reject_outliers(
    ids: np.ndarray, px: np.ndarray, target: Target
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remove, one at a time, the worst corner above ``OUTLIER_THRESHOLD_PX``."""
    rejected = []
    while len(ids) >= 7:
        res = _local_residuals(ids, px, target)
        worst = int(np.argmax(res))
        if res[worst] <= OUTLIER_THRESHOLD_PX:
            break
        rejected.append(int(ids[worst]))
        ids, px = np.delete(ids, worst), np.delete(px, worst, axis=0)
    return ids, px, np.array(rejected, dtype=np.int64)


def _report(
    shape: tuple[int, int],
    target: Target,
    ids: np.ndarray,
    px: np.ndarray,
    reasons: list[str],
    min_corners: int,
) -> DetectionReport:
    rejected = np.zeros(0, dtype=np.int64)
    rms = float("nan")
    coverage = 0.0
    if len(ids):
        order = np.argsort(ids, kind="stable")
        ids, px = ids[order], px[order]
        ids, px, rejected = _reject_outliers(ids, px, target)
        H = _homography(target.points_m[ids, :2], px)
        if H is not None:
            r = _apply_h(H, target.points_m[ids, :2]) - px
            rms = float(np.sqrt(np.mean(np.sum(r * r, axis=1))))
        elif len(ids) >= 4:
            reasons.append("corners are collinear: the board is barely in view")
        if len(ids) >= 3:
            hull = cv2.convexHull(px.astype(np.float32))
            coverage = float(cv2.contourArea(hull)) / float(shape[0] * shape[1])
    if len(ids) < min_corners and (len(ids) or not reasons):
        msg = f"only {len(ids)} corners kept, fewer than min_corners={min_corners}"
        if len(rejected):
            msg += f" ({len(rejected)} rejected by the homography check)"
        reasons.append(msg)
    return DetectionReport(
        Detection(ids, px),
        ok=not reasons,
        reasons=tuple(reasons),
        homography_rms_px=rms,
        coverage=coverage,
        rejected_ids=rejected,
    )

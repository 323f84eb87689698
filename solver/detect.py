"""Target detection: corner ids and pixels of a ChArUco board, a chessboard, an AprilGrid or
AprilTags in one image (ids and board frame of ``solver/problem.py``; pixel (0, 0) is the centre
of the top-left pixel, OpenCV's convention). Colour images: the green channel. Which OpenCV
detector, refinement and window each target gets, and why, is ``docs/results/DETECTION.md``.

A chessboard must be whole in view. Its corner order under the board's symmetries: (1) the board
is seen from its printed side (``x`` cross ``y`` > 0 in the image, v down); (2) the square next
to corner 0 is black; (3) a board still symmetric (``squares_x + squares_y`` even: it looks the
same after a half turn, :func:`half_turn_symmetric`) takes the corner 0 that makes its +x axis
point most to the right. Rule 3 is a guess: :func:`resolve_half_turns` decides each frame's half
turn before a solve.

When nothing usable is found, the report says what was seen. A local homography check removes
grossly wrong corners and lists them in ``rejected_ids``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from functools import lru_cache

import cv2
import numpy as np

from slidecal.solver.errors import DegenerateError, InputError
from slidecal.solver.geometry import R_from_rvec, Rz, T_from_Rt
from slidecal.solver.problem import CalibrationProblem, Detection, Target

# Local homography check: a corner farther than this from its grid neighbours' homography is
# rejected (a lens departs from one by about a pixel; a gross error is a marker margin or more).
OUTLIER_THRESHOLD_PX = 3.0
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 60, 1e-3)
_MAX_HALF_WINDOW_PX = 8
_MIN_HALF_WINDOW_PX = 2


@dataclass(frozen=True)
class DetectionReport:
    """What ``detect`` found in one image.

    ``detection``: ids (n,) and pixels (n, 2) (empty when nothing usable; its ``reason`` is the
    ``diagnosis``). ``ok``: usable for calibration. ``reasons``: why not (empty when ok).
    ``homography_rms_px``: rms residual of one homography fitted to all kept corners (non-zero
    with lens distortion; nan below 4 corners). ``coverage``: fraction of the image area inside
    the corners' convex hull. ``rejected_ids``: corners removed by the local homography check.
    ``path``: the detector step that found the corners ("" when none did). ``blur_sigma_px``:
    edge width of the image (std of the Gaussian blur that explains its steepest edges).
    ``saturated_fraction``: fraction of pixels at 255.
    """

    detection: Detection
    ok: bool
    reasons: tuple[str, ...]
    homography_rms_px: float
    coverage: float
    rejected_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    path: str = ""
    blur_sigma_px: float = float("nan")
    saturated_fraction: float = float("nan")

    @property
    def diagnosis(self) -> str:
        """The reasons as one line ("" when ok)."""
        return "; ".join(self.reasons)


def charuco_board(target: Target, legacy: bool = False) -> cv2.aruco.CharucoBoard:
    """OpenCV's ``CharucoBoard`` for a ``charuco`` target (same layout and corner ids);
    ``legacy``: the layout of OpenCV before 4.6 (see :func:`_detect_charuco`)."""
    return _charuco_board(_charuco_key(target), legacy)


#: (squares_x, squares_y, square_size_m, marker_size_m, dictionary) of a ChArUco target
CharucoKey = tuple[int, int, float, float, str]


def _charuco_key(target: Target) -> CharucoKey:
    return (
        target.squares_x,
        target.squares_y,
        target.square_size_m,
        target.marker_size_m,
        target.dictionary or "DICT_5X5_100",
    )


@lru_cache(maxsize=8)
def _charuco_board(key: CharucoKey, legacy: bool = False) -> cv2.aruco.CharucoBoard:
    squares_x, squares_y, square_m, marker_m, dictionary = key
    d = _dictionary(dictionary, "ArUco dictionary", "DICT_5X5_100")
    if not 0.0 < marker_m < square_m:
        raise InputError(
            f"marker_size_m ({marker_m}) must be positive and smaller than square_size_m "
            f"({square_m})"
        )
    board = cv2.aruco.CharucoBoard((squares_x, squares_y), square_m, marker_m, d)
    if legacy:
        board.setLegacyPattern(True)
    return board


def _dictionary(name: str, what: str, example: str) -> cv2.aruco.Dictionary:
    """OpenCV's predefined dictionary ``name``; an ``InputError`` naming it (``what``, e.g. "tag
    family", and an ``example`` of a valid name) when OpenCV has none of that name."""
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise InputError(f"unknown {what} {name!r}; use an OpenCV name such as {example}")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))


@lru_cache(maxsize=8)
def _charuco_detector(key: CharucoKey, legacy: bool = False) -> cv2.aruco.CharucoDetector:
    board = _charuco_board(key, legacy)
    cp = cv2.aruco.CharucoParameters()
    cp.minMarkers = 1  # a corner next to one decoded marker; wrong ids are caught afterwards
    cp.tryRefineMarkers = True
    dp = cv2.aruco.DetectorParameters()
    dp.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    dp.cornerRefinementWinSize = 4
    dp.cornerRefinementMaxIterations = 50
    dp.cornerRefinementMinAccuracy = 0.01
    return cv2.aruco.CharucoDetector(board, cp, dp)


COLOUR_CONVERSIONS = ("green", "luma", "mean")
COLOUR_CONVERSION = "green"  # measured in docs/results/DETECTION.md (chromatic aberration)


#: The percentiles of a non-8-bit image mapped to 0 and 255 (:func:`grey_of`)
GREY_RANGE_PERCENTILES = (0.01, 99.99)


def grey_of(image: np.ndarray, colour: str = COLOUR_CONVERSION) -> np.ndarray:
    """uint8 (H, W) of an (H, W) grey or (H, W, 3|4) BGR(A) image.

    ``colour``: "green" (the G channel), "luma" (OpenCV's BGR2GRAY mix) or "mean" (the
    channels' mean). Other dtypes are rescaled to 0..255 between their
    ``GREY_RANGE_PERCENTILES``.
    """
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] in (3, 4):
        if colour == "green":
            img = img[:, :, 1]
        elif colour == "luma":
            code = cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
            img = cv2.cvtColor(np.ascontiguousarray(img), code)
        elif colour == "mean":
            img = img[:, :, :3].astype(np.float64).mean(axis=2)
            if np.asarray(image).dtype == np.uint8:
                img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        else:
            raise InputError(
                f"colour conversion {colour!r} unknown; use one of {COLOUR_CONVERSIONS}"
            )
    if img.ndim != 2 or min(img.shape) < 8:
        raise InputError(f"image must be (H, W) grey or (H, W, 3) BGR, got shape {np.shape(image)}")
    if img.dtype != np.uint8:
        f = img.astype(np.float64)
        lo, hi = (float(x) for x in np.percentile(f, GREY_RANGE_PERCENTILES))
        scale = 255.0 / (hi - lo) if hi > lo else 0.0
        img = np.clip((f - lo) * scale, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(img)


# Image checks, reported when the target is not found: the levels at which OpenCV's detectors
# start to fail on rendered boards (docs/results/DETECTION.md).
DARK_MEAN_GREY = 25.0
SATURATED_FRACTION = 0.25
BLURRED_SIGMA_PX = 2.5


def image_stats(grey: np.ndarray) -> tuple[float, float, float]:
    """(mean grey level, fraction of pixels at 255, edge width in px) of a uint8 image.

    Edge width: a step of contrast ``C`` blurred by a Gaussian of std ``sigma`` has a steepest
    gradient ``C / (sqrt(2 pi) sigma)``; ``C`` is the 1st-99th percentile range and the
    steepest gradient the 99.9th percentile of the gradient magnitude (Sobel, per pixel), all
    computed on the image reduced as for detection (``reduction_factor``) and scaled back.
    """
    step = reduction_factor(grey.shape)
    small = _reduce(grey, step)
    hist = np.bincount(small.ravel(), minlength=256).astype(np.float64)
    cdf = np.cumsum(hist) / hist.sum()
    mean = float(np.arange(256) @ hist / hist.sum())
    saturated = float(hist[255] / hist.sum())
    lo, hi = (float(np.searchsorted(cdf, q)) for q in (0.01, 0.99))
    f = small.astype(np.float32)
    gx = cv2.Sobel(f, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    gy = cv2.Sobel(f, cv2.CV_32F, 0, 1, ksize=3) / 8.0
    mag = cv2.magnitude(gx, gy).ravel()
    k = int(0.999 * (len(mag) - 1))
    steep = float(np.partition(mag, k)[k])
    contrast = hi - lo
    if contrast < 8.0 or steep <= 0.0:
        sigma = float("inf")
    else:
        # the 3x3 Sobel and the box of the reduction add their own width (0.5 px, step / sqrt(12))
        sigma_small = contrast / (np.sqrt(2.0 * np.pi) * steep)
        sigma = step * float(np.sqrt(max(sigma_small**2 - 0.5**2, 0.0)))
    return mean, saturated, sigma


MIN_CORNERS = 4  # one tag's corners: the least that fixes a homography (a board pose)


def detect(
    image: np.ndarray,
    target: Target,
    *,
    min_corners: int = MIN_CORNERS,
    colour: str = COLOUR_CONVERSION,
) -> DetectionReport:
    """Find the target's corners in ``image``; never raises for an image without the target.

    ``image``: uint8 (H, W) grey or (H, W, 3) BGR (other dtypes are rescaled to 0..255);
    ``target``: a ``charuco``, ``chessboard``, ``apriltag`` or ``aprilgrid`` target; fewer kept
    corners than ``min_corners`` (at least 4) make the frame unusable; ``colour``: how a colour
    image becomes grey ("green", "luma" or "mean"). Returns the ids, pixels and diagnostics.
    """
    grey = grey_of(image, colour)
    stats = image_stats(grey)
    if target.kind == "charuco":
        ids, px, reasons, path = _detect_charuco(grey, target, stats[2])
    elif target.kind == "chessboard":
        ids, px, reasons, path = _detect_chessboard(grey, target)
    elif target.kind in ("apriltag", "aprilgrid"):
        ids, px, reasons, path = (*_detect_tags(grey, target), "aruco")
    else:
        raise InputError(
            f"cannot detect a target of kind {target.kind!r} in images; give its detections in "
            "the session file instead"
        )
    if not len(ids):
        path = ""
    return _report(grey, target, ids, px, list(reasons), min_corners, path, stats)


def _empty() -> tuple[np.ndarray, np.ndarray]:
    return np.zeros(0, dtype=np.int64), np.zeros((0, 2))


def _detect_charuco(
    grey: np.ndarray, target: Target, blur_px: float = 0.0
) -> tuple[np.ndarray, np.ndarray, list, str]:
    """The ChArUco corners, the reasons when none, and the path ("charuco", or
    "charuco-legacy": a board of OpenCV's layout before 4.6, docs/results/DETECTION.md)."""
    ids, px, reasons, n_markers = _detect_charuco_layout(grey, target, blur_px, legacy=False)
    if target.squares_y % 2 == 0 and n_markers >= 2 and len(ids) < n_markers / 2:
        old = _detect_charuco_layout(grey, target, blur_px, legacy=True)
        if len(old[0]) > len(ids):
            return *old[:3], "charuco-legacy"
    return ids, px, reasons, "charuco"


def _detect_charuco_layout(
    grey: np.ndarray, target: Target, blur_px: float, legacy: bool
) -> tuple[np.ndarray, np.ndarray, list, int]:
    """The corners of one layout, the reasons when none, and how many markers decoded."""
    key = _charuco_key(target)
    detector = _charuco_detector(key, legacy)
    board = _charuco_board(key, legacy)
    ch_corners, ch_ids, m_corners, m_ids = detector.detectBoard(grey)
    if m_ids is None or len(m_ids) == 0:
        # (the old layout is tried only after markers were found: this is the first try)
        why = other_family(grey, target.dictionary)
        if not why:
            size = (target.squares_x - 1, target.squares_y - 1)
            if _classic(_reduce(grey, reduction_factor(grey.shape)), size) is not None:
                why = (
                    f"but a chessboard of {size[0]} x {size[1]} inner corners without markers "
                    "is in view: if the board has no markers, set target.kind to chessboard"
                )
        return (
            *_empty(),
            [
                f"no ArUco marker of {target.dictionary} found, {why}"
                if why
                else "no ArUco marker of the target found (board not in view, seen from "
                "its back, or too blurred/dark)"
            ],
            0,
        )
    if ch_ids is None or len(ch_ids) == 0:
        return (
            *_empty(),
            [
                f"{len(m_ids)} markers found but no ChArUco corner could be interpolated "
                "(check squares_x, squares_y and the dictionary against the board)"
            ],
            len(m_ids),
        )
    ids = np.asarray(ch_ids, dtype=np.int64).reshape(-1)
    px = np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2)
    # marker corners (board frame) against their image positions, to size the refinement
    # windows (CharucoBoard.matchImagePoints takes ChArUco corners, not marker corners)
    index = {int(m): k for k, m in enumerate(np.asarray(board.getIds()).reshape(-1))}
    board_obj = board.getObjPoints()
    markers: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for mc, mid in zip(m_corners, np.asarray(m_ids).reshape(-1), strict=True):
        if int(mid) in index:
            k = index[int(mid)]
            obj = np.asarray(board_obj[k], dtype=np.float64).reshape(4, 3)[:, :2]
            markers[k] = (obj, np.asarray(mc, dtype=np.float64).reshape(4, 2))
    if markers:
        H = _homography(
            np.concatenate([o for o, _ in markers.values()]),
            np.concatenate([i for _, i in markers.values()]),
        )
        if H is not None:
            px = _refine_charuco(grey, target, board, ids, px, markers, H, blur_px)
    return ids, px, [], len(m_ids)


def _refine_charuco(
    grey: np.ndarray,
    target: Target,
    board: cv2.aruco.CharucoBoard,
    ids: np.ndarray,
    px: np.ndarray,
    markers: dict[int, tuple[np.ndarray, np.ndarray]],
    H: np.ndarray,
    blur_px: float = 0.0,
) -> np.ndarray:
    """``cornerSubPix`` per corner with the largest window that holds no marker edge (the
    outlines mapped by the adjacent markers' homography, else the board-wide ``H``); a corner
    whose window is narrower than 1.5 times the image's blur ``blur_px`` keeps its estimate."""
    sq, m = target.square_size_m, target.marker_size_m
    g = 0.5 * (sq - m)
    t = g + np.linspace(0.0, 1.0, 9) * m
    outline = np.concatenate(
        [np.stack([sx * t, np.full_like(t, sy * g)], axis=1) for sx in (-1, 1) for sy in (-1, 1)]
        + [np.stack([np.full_like(t, sx * g), sy * t], axis=1) for sx in (-1, 1) for sy in (-1, 1)]
    )
    centres = np.array(
        [np.asarray(o).reshape(4, 3)[:, :2].mean(axis=0) for o in board.getObjPoints()]
    )
    dist = np.full(len(ids), np.inf)
    for i, (cid, p0) in enumerate(zip(ids, px, strict=True)):
        P = target.points_m[cid, :2]
        near = np.flatnonzero(np.all(np.abs(centres - P) < 0.75 * sq, axis=1))
        seen = [markers[k] for k in near if k in markers]
        Hl = None
        if seen:
            Hl = _homography(
                np.concatenate([o for o, _ in seen]), np.concatenate([q for _, q in seen])
            )
        q = _apply_h(Hl if Hl is not None else H, P + outline)
        dist[i] = float(np.min(np.max(np.abs(q - p0), axis=1)))
    # keep the blurred marker edge (~2 px) out of the (2 w + 1) window
    half = np.floor(dist - 2.0).astype(int)
    smallest = max(float(_MIN_HALF_WINDOW_PX), 1.5 * blur_px if np.isfinite(blur_px) else 0.0)
    # too close to a marker to refine reliably: the detector's estimate stays
    return _subpix(grey, px, np.where(half < smallest, 0, np.minimum(half, _MAX_HALF_WINDOW_PX)))


def _subpix(grey: np.ndarray, px: np.ndarray, half: np.ndarray) -> np.ndarray:
    """``cornerSubPix`` of the corners ``px`` (n, 2), each in a window of half-width ``half``
    (n,); a corner of half-width 0 stays where it is."""
    out = px.copy()
    for w in np.unique(half[half > 0]):
        sel = half == w
        c = px[sel].astype(np.float32).reshape(-1, 1, 2)
        r = cv2.cornerSubPix(grey, c, (int(w), int(w)), (-1, -1), _SUBPIX_CRITERIA)
        out[sel] = np.asarray(r, dtype=np.float64).reshape(-1, 2)
    return out


# Classic detector on the reduced image: adaptive threshold, and the quick check that gives up
# at once on images without a board; never CALIB_CB_NORMALIZE_IMAGE for SB (see the docstring).
_CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_FAST_CHECK
REDUCED_LONG_SIDE_PX = 1000
SUBPIX_WINDOW_FRACTION = 0.3
_SUBPIX_HALF_WINDOW_PX = (3, 25)


def reduction_factor(shape: tuple[int, int]) -> int:
    """Integer factor that brings the image's long side to about ``REDUCED_LONG_SIDE_PX``."""
    return max(1, int(round(max(shape) / REDUCED_LONG_SIDE_PX)))


def _reduce(grey: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return grey
    h, w = grey.shape
    return cv2.resize(grey, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def _classic(img: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    found, corners = cv2.findChessboardCorners(img, size, flags=_CLASSIC_FLAGS)
    return np.asarray(corners, np.float64).reshape(-1, 2) if found and corners is not None else None


def _sb(img: np.ndarray, size: tuple[int, int], flags: int = 0) -> np.ndarray | None:
    found, corners = cv2.findChessboardCornersSB(img, size, flags=flags)
    return np.asarray(corners, np.float64).reshape(-1, 2) if found and corners is not None else None


#: the local-contrast scale of ``flatten_light``, in pixels of the reduced image
FLATTEN_SIGMA_PX = 10.0


def flatten_light(grey: np.ndarray, sigma_px: float = FLATTEN_SIGMA_PX) -> np.ndarray:
    """``grey`` with its light made even: each pixel's difference from the local mean over the
    local standard deviation (Gaussian windows of ``sigma_px``), mapped to 0..255. A glare or a
    light gradient that lifts the black squares towards the white ones leaves the pattern's
    local contrast, which the classic detector's adaptive threshold then finds again."""
    g = grey.astype(np.float32)
    d = g - cv2.GaussianBlur(g, (0, 0), sigma_px)
    s = np.sqrt(cv2.GaussianBlur(d * d, (0, 0), sigma_px)) + 2.0  # + 2: flat areas stay grey
    return np.clip(128.0 + 50.0 * d / s, 0, 255).astype(np.uint8)


CHESSBOARD_PATHS = (
    "classic_reduced",
    "classic_flat_reduced",
    "sb_reduced",
    "sb_full",
    "sb_exhaustive_reduced",
)


def find_chessboard(
    grey: np.ndarray, size: tuple[int, int], paths: tuple[str, ...] = CHESSBOARD_PATHS
) -> tuple[np.ndarray | None, str]:
    """Unrefined corners (n, 2) in full-resolution pixels of a ``size`` = (cols, rows) inner
    corner chessboard by the first of ``paths`` that finds it, and that path's name."""
    f = reduction_factor(grey.shape)
    small = _reduce(grey, f)
    for path in paths:
        full = path.endswith("_full")
        img = grey if full else small
        if path == "classic_reduced":
            c = _classic(img, size)
        elif path == "classic_flat_reduced":
            c = _classic(flatten_light(small), size)
        elif path == "sb_reduced" or (path == "sb_full" and f > 1):  # f = 1: sb_reduced's image
            c = _sb(img, size)
        elif path == "sb_full":
            continue
        elif path == "sb_exhaustive_reduced":
            c = _sb(img, size, cv2.CALIB_CB_EXHAUSTIVE)
        else:
            raise InputError(f"unknown chessboard detector path {path!r}")
        if c is not None:  # the reduced image's pixel centres taken to full resolution
            return (c if full else (c + 0.5) * f - 0.5), path
    return None, ""


def refine_grid(grey: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``cornerSubPix`` of a (rows, cols, 2) corner grid at full resolution, each corner in a
    window of ``SUBPIX_WINDOW_FRACTION`` times the distance to its nearest grid neighbour."""
    rows, cols = grid.shape[:2]
    d = np.full((rows, cols), np.inf)
    if cols > 1:
        dx = np.linalg.norm(np.diff(grid, axis=1), axis=2)
        d[:, :-1] = np.minimum(d[:, :-1], dx)
        d[:, 1:] = np.minimum(d[:, 1:], dx)
    if rows > 1:
        dy = np.linalg.norm(np.diff(grid, axis=0), axis=2)
        d[:-1] = np.minimum(d[:-1], dy)
        d[1:] = np.minimum(d[1:], dy)
    lo, hi = _SUBPIX_HALF_WINDOW_PX
    half = np.clip(np.floor(SUBPIX_WINDOW_FRACTION * d), lo, hi).astype(int).ravel()
    return _subpix(grey, grid.reshape(-1, 2), half).reshape(rows, cols, 2)


def _detect_chessboard(
    grey: np.ndarray, target: Target
) -> tuple[np.ndarray, np.ndarray, list, str]:
    cols, rows = target.squares_x - 1, target.squares_y - 1
    corners, path = find_chessboard(grey, (cols, rows))
    if corners is None:
        return *_empty(), [_chessboard_not_found(grey, target)], ""
    grid = corners.reshape(rows, cols, 2)
    grid = _orient_chessboard(grey, grid)
    if grid is None:
        return (
            *_empty(),
            [
                "chessboard found but its orientation is inconsistent (seen in a "
                "mirror or from the back?)"
            ],
            path,
        )
    grid = refine_grid(grey, grid)
    ids = np.arange(rows * cols, dtype=np.int64)
    return ids, grid.reshape(-1, 2), [], path


def _chessboard_not_found(grey: np.ndarray, target: Target) -> str:
    """What was seen where the expected chessboard was not: another board size, or nothing."""
    cols, rows = target.squares_x - 1, target.squares_y - 1
    small = _reduce(grey, reduction_factor(grey.shape))
    found, corners, meta = cv2.findChessboardCornersSBWithMeta(small, (3, 3), cv2.CALIB_CB_LARGER)
    if found and meta is not None and corners is not None:
        r, c = (int(v) for v in np.shape(meta)[:2])
        if (min(r, c), max(r, c)) != (min(rows, cols), max(rows, cols)):
            a, b = (c, r) if (cols >= rows) == (c >= r) else (r, c)
            return (
                f"a chessboard of {a} x {b} inner corners was found where {cols} x {rows} were "
                f"expected: if that is the whole board, set squares_x: {a + 1}, squares_y: "
                f"{b + 1} (squares, one more than inner corners); otherwise bring the whole "
                "board into view"
            )
        return (
            f"a chessboard of {cols} x {rows} inner corners is visible but could not be "
            "measured; check focus and lighting"
        )
    return (
        f"no chessboard found (expected {cols} x {rows} inner corners, squares_x: "
        f"{target.squares_x}, squares_y: {target.squares_y}); the whole board must be in "
        "view, seen from its printed side"
    )


TAG_REFINEMENTS = ("edges", "subpix", "apriltag", "none")
# an AprilGrid's tag corners are X-junctions (``cornerSubPix`` is unbiased on them); a lone
# tag's are L-corners, taken as the intersections of its fitted border edges
TAG_REFINEMENT = {"apriltag": "edges", "aprilgrid": "subpix"}


#: The marker families :func:`other_family` tries when none of the target's is found: each
#: ArUco size by its largest dictionary (the smaller ones are its first 50, 100, 250 markers),
#: the original ArUco set, and the AprilTag families OpenCV decodes
_FAMILIES = (
    "DICT_4X4_1000",
    "DICT_5X5_1000",
    "DICT_6X6_1000",
    "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
    "DICT_APRILTAG_16h5",
    "DICT_APRILTAG_25h9",
    "DICT_APRILTAG_36h10",
    "DICT_APRILTAG_36h11",
    "DICT_ARUCO_MIP_36h12",
)
#: Fewest markers of another family that make :func:`other_family` name it (one can be a
#: texture that happens to decode, in the small families most)
_OTHER_FAMILY_MIN_MARKERS = 3


def other_family(grey: np.ndarray, dictionary: str) -> str:
    """Why no marker of ``dictionary`` was found when markers of another family are in view:
    the family with the most markers (at least ``_OTHER_FAMILY_MIN_MARKERS``) and the
    smallest dictionary of it that holds every id seen, as a sentence; "" when none is (looked
    for on the reduced image)."""
    img = _reduce(grey, reduction_factor(grey.shape))
    # the dictionary's family: DICT_6X6_250 -> DICT_6X6_1000
    own = re.sub(r"^(DICT_[4-7]X[4-7])_\d+$", r"\1_1000", dictionary)
    best: tuple[int, str, int] = (0, "", 0)
    for family in _FAMILIES:
        if family == own:
            continue
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, family))
        _, ids, _ = cv2.aruco.ArucoDetector(d, cv2.aruco.DetectorParameters()).detectMarkers(img)
        n = 0 if ids is None else len(ids)
        if n > best[0]:
            best = (n, family, int(np.max(ids)))
    n, family, top = best
    if n < _OTHER_FAMILY_MIN_MARKERS:
        return ""
    name = family
    if family.endswith("_1000"):
        size = next(k for k in (50, 100, 250, 1000) if top < k)
        name = f"{family[: -len('1000')]}{size}"
    return (
        f"but {n} markers of {name} are in view (ids up to {top}): set target.dictionary to "
        f"{name} (or to the larger dictionary of its family that the board was made with)"
    )


#: ``minMarkerDistanceRate`` of the second look for tags the first missed (OpenCV's default
#: groups a tag on a narrow margin with its paper's outline and may lose it).
TAG_RETRY_MARKER_DISTANCE_RATE = 0.02


@lru_cache(maxsize=16)
def _tag_detector(
    dictionary: str, refinement: str, marker_distance_rate: float = 0.0
) -> cv2.aruco.ArucoDetector:
    """OpenCV's marker detector for a tag family; ``marker_distance_rate`` > 0 sets
    ``minMarkerDistanceRate`` (0: OpenCV's default)."""
    d = _dictionary(dictionary, "tag family", "DICT_APRILTAG_36h11")
    dp = cv2.aruco.DetectorParameters()
    if marker_distance_rate > 0.0:
        dp.minMarkerDistanceRate = marker_distance_rate
    if refinement == "apriltag":
        dp.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    else:
        dp.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE  # refined below, per tag
    return cv2.aruco.ArucoDetector(d, dp)


def _detect_tags(
    grey: np.ndarray, target: Target, refinement: str = ""
) -> tuple[np.ndarray, np.ndarray, list]:
    """Corners of the target's AprilTags: each decoded tag of the target gives 4 corners."""
    refinement = refinement or TAG_REFINEMENT[target.kind]
    family = target.dictionary or "DICT_APRILTAG_36h11"
    corners, tag_ids = _find_tags(grey, family, refinement, set(target.tag_corner_ids()))
    if len(tag_ids) == 0:
        why = other_family(grey, family)
        return *_empty(), [
            f"no tag of family {family} found, {why}"
            if why
            else f"no tag of family {family} found (target not in view, seen from its back, "
            "too small, blurred or dark)"
        ]
    wanted = target.tag_corner_ids()
    ids, px, strangers = [], [], []
    for c, t in zip(corners, tag_ids, strict=True):
        if int(t) not in wanted:
            strangers.append(int(t))
            continue
        q = np.asarray(c, dtype=np.float64).reshape(4, 2)
        if refinement in ("subpix", "edges"):
            q = _refine_tag(grey, q, target)
        if refinement == "edges":
            q = _tag_edge_corners(grey, q, _tag_cells(target))
        ids.append(wanted[int(t)])
        px.append(q)
    if not ids:
        return *_empty(), [
            f"tags {sorted(strangers)} of family {family} found, none of the target's tags "
            f"{list(target.tag_ids)[:8]}: check tag_ids (or tag_cols/tag_rows)"
        ]
    ids_a, px_a = np.concatenate(ids).astype(np.int64), np.concatenate(px)
    if target.kind == "aprilgrid" and refinement == "subpix":
        ids_a, px_a = _recover_grid_tags(grey, target, ids_a, px_a)
    return ids_a, px_a, []


def _find_tags(
    grey: np.ndarray, family: str, refinement: str, wanted: set[int]
) -> tuple[list[np.ndarray], list[int]]:
    """The decoded tags (corners (4, 2) each, ids): OpenCV's detector, and for a tag of
    ``wanted`` it missed a second look (:data:`TAG_RETRY_MARKER_DISTANCE_RATE`); one quad per
    id, the largest (a tag's outer border)."""
    found: dict[int, np.ndarray] = {}
    for rate in (0.0, TAG_RETRY_MARKER_DISTANCE_RATE):
        corners, ids, _ = _tag_detector(family, refinement, rate).detectMarkers(grey)
        seen: dict[int, np.ndarray] = {}
        for c, t in zip(corners, [] if ids is None else np.asarray(ids).reshape(-1), strict=True):
            q = np.asarray(c, dtype=np.float64).reshape(4, 2)
            area = cv2.contourArea(q.astype(np.float32))  # the largest: the tag's outer border
            if int(t) not in seen or area > cv2.contourArea(seen[int(t)].astype(np.float32)):
                seen[int(t)] = q
        for t, q in seen.items():
            found.setdefault(t, q)
        if wanted <= set(found):
            break
    return list(found.values()), list(found)


def _recover_grid_tags(
    grey: np.ndarray, target: Target, ids: np.ndarray, px: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Tags of an AprilGrid the marker detector missed, predicted by a homography on the found
    tags around them, refined like found ones and kept only if the tag's cells read back as its
    own code (at most 3 of its bits wrong; the 36h11 codes differ in at least 11)."""
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, target.dictionary))
    cells = d.markerSize + 2
    corner_ids = target.tag_corner_ids()
    found = {int(t) for t, c in corner_ids.items() if np.isin(c, ids).all()}
    if len(found) < 2:
        return ids, px
    pos = dict(zip(ids.tolist(), px, strict=True))
    xy = target.points_m[:, :2]
    h, w = grey.shape
    new_ids, new_px = [ids], [px]
    for t in sorted(set(corner_ids) - found):
        ti, tk = divmod(t, target.tag_cols)
        near = [
            f
            for f in found
            if max(abs(f // target.tag_cols - ti), abs(f % target.tag_cols - tk)) <= 2
        ]
        if len(near) < 2:
            near = sorted(found)
        src = np.concatenate([corner_ids[f] for f in near])
        H = _homography(xy[src], np.array([pos[int(i)] for i in src]))
        if H is None:
            continue
        q = _apply_h(H, xy[corner_ids[t]])
        side = float(np.mean(np.linalg.norm(q - np.roll(q, 1, axis=0), axis=1)))
        if (
            side < 2.0 * cells
            or np.any(q < 2)
            or np.any(q[:, 0] > w - 3)
            or np.any(q[:, 1] > h - 3)
        ):
            continue
        r = _refine_tag(grey, q, target)
        if np.max(np.linalg.norm(r - q, axis=1)) > 1.5 * side / cells:
            continue
        if _code_errors(grey, r, d, t, cells) > 3:
            continue
        new_ids.append(corner_ids[t])
        new_px.append(r)
    return np.concatenate(new_ids), np.concatenate(new_px)


def _code_errors(
    grey: np.ndarray, q: np.ndarray, d: cv2.aruco.Dictionary, tag: int, cells: int
) -> int:
    """Cells (border included) of the quad ``q`` (TL, TR, BR, BL) that differ from tag ``tag``."""
    bits = cv2.aruco.generateImageMarker(d, int(tag), cells, borderBits=1) > 127
    unit = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    H = cv2.getPerspectiveTransform(unit.astype(np.float32), q.astype(np.float32))
    c = (np.arange(cells) + 0.5) / cells
    u, v = np.meshgrid(c, c)
    p = _apply_h(H, np.column_stack([u.ravel(), v.ravel()]))
    sample = cv2.remap(
        grey.astype(np.float32),
        p[:, 0].astype(np.float32).reshape(1, -1),
        p[:, 1].astype(np.float32).reshape(1, -1),
        cv2.INTER_LINEAR,
    ).reshape(cells, cells)
    lo, hi = np.percentile(sample, [10.0, 90.0])
    return int(np.sum((sample > 0.5 * (lo + hi)) != bits))


def _tag_cells(target: Target) -> float:
    """Cells across one tag, its black border included (8 for the 36h11 family)."""
    if target.dictionary:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, target.dictionary))
        return float(d.markerSize + 2)
    return 8.0


#: Edge points per tag side used by the edge fit (fewer: the side is too short or blurred, and
#: the tag keeps its ``cornerSubPix`` corners)
_MIN_EDGE_POINTS = 8


def _side_curve(
    grey: np.ndarray, a: np.ndarray, b: np.ndarray, centre: np.ndarray, half_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The border edge of a tag between corners ``a`` and ``b`` as ``a + t u + f(t) n`` (``n``
    out of the tag, ``f`` quadratic), from profiles ``half_px`` each way across the side
    (docs/results/DETECTION.md, "One AprilTag"). Returns (a, u, n, coefficients) or None."""
    length = float(np.linalg.norm(b - a))
    u = (b - a) / length
    n = np.array([-u[1], u[0]])
    if np.dot(n, 0.5 * (a + b) - centre) < 0:
        n = -n
    t = np.linspace(0.12, 0.88, max(int(length / 2), _MIN_EDGE_POINTS)) * length
    s = np.arange(-half_px, half_px + 1e-9, 0.25)
    P = a + t[:, None, None] * u + s[None, :, None] * n
    prof = cv2.remap(  # cubic: a linear interpolation locks an edge along a pixel row or
        grey,  # column to the grid
        P[..., 0].astype(np.float32),
        P[..., 1].astype(np.float32),
        cv2.INTER_CUBIC,
    ).astype(np.float64)
    k = max(len(s) // 5, 2)
    dark, bright = np.median(prof[:, :k], axis=1), np.median(prof[:, -k:], axis=1)
    p = prof - 0.5 * (dark + bright)[:, None]
    up = (p[:, :-1] < 0) & (p[:, 1:] >= 0)
    one = (np.sum(up, axis=1) == 1) & (bright - dark > 10.0)
    if np.sum(one) < _MIN_EDGE_POINTS:
        return None
    j = np.argmax(up[one], axis=1)
    rows = np.flatnonzero(one)
    p0, p1 = p[rows, j], p[rows, j + 1]
    off = s[j] + 0.25 * (-p0) / (p1 - p0)
    tt = t[rows]
    keep = np.ones(len(tt), dtype=bool)
    coef = np.zeros(3)
    for _ in range(3):
        coef = np.polyfit(tt[keep], off[keep], 2)
        r = off - np.polyval(coef, tt)
        mad = 1.4826 * float(np.median(np.abs(r[keep])))
        keep = np.abs(r) < max(3.0 * mad, 0.05)
        if np.sum(keep) < _MIN_EDGE_POINTS:
            return None
    return a, u, n, coef


#: How deep, in border cells, a lone tag's edge profiles reach each way (in, into the black
#: border; out, into the white margin), the cell taken at the side's narrow end: a side
#: foreshortened by a tilt keeps its profiles out of the data cells next to the border.
TAG_EDGE_DEPTH = 0.7


def _tag_edge_corners(grey: np.ndarray, q: np.ndarray, cells: float) -> np.ndarray:
    """A lone tag's corners (4, 2) as the intersections of its fitted border edges (unbiased
    where ``cornerSubPix`` pulls L-corners inwards); the corners ``q`` when a side cannot be
    fitted."""
    centre = q.mean(axis=0)
    grey_f = grey.astype(np.float32)  # interpolated profiles without 8-bit rounding
    curves = []
    for i in range(4):
        a, b = q[i], q[(i + 1) % 4]
        u = (b - a) / max(float(np.linalg.norm(b - a)), 1e-9)
        n = np.array([-u[1], u[0]])
        # the border cell's width at the side's narrow end (perspective narrows one end): the
        # profiles reach no deeper, or the tag's data cells would enter their dark level
        across = min(abs(float(np.dot(q[i - 1] - a, n))), abs(float(np.dot(q[i - 2] - b, n))))
        half = max(TAG_EDGE_DEPTH * across / cells, 2.0)
        curves.append(_side_curve(grey_f, a, b, centre, half))
    if any(c is None for c in curves):
        return q
    out = q.copy()
    for i in range(4):
        x = q[i].copy()
        for _ in range(5):  # Newton on the two curves' equations dot(x - a, n) = f(dot(x - a, u))
            rows, rhs = [], []
            for a, u, n, coef in (curves[i - 1], curves[i]):
                t = float(np.dot(x - a, u))
                rows.append(n - np.polyval(np.polyder(coef), t) * u)
                rhs.append(np.polyval(coef, t) - float(np.dot(x - a, n)))
            try:
                x = x + np.linalg.solve(np.array(rows), np.array(rhs))
            except np.linalg.LinAlgError:
                return q
        if not np.all(np.isfinite(x)) or np.linalg.norm(x - q[i]) > half:
            return q
        out[i] = x
    return out


#: Farthest a tag corner may move in its last ``cornerSubPix`` pass, in cells of the tag (and
#: at least :data:`TAG_SUBPIX_JUMP_MIN_PX`): farther, the paper's corner pulled the window.
TAG_SUBPIX_JUMP_CELLS = 0.25
TAG_SUBPIX_JUMP_MIN_PX = 2.0
#: How far a lone tag's ``cornerSubPix`` window reaches each way, in cells (an AprilGrid's: 0.8
#: of its limit): short of a usual one-cell paper margin, whose corner would pull the tag's.
TAG_SUBPIX_WINDOW_CELLS = 0.6


def _refine_tag(grey: np.ndarray, q: np.ndarray, target: Target) -> np.ndarray:
    """``cornerSubPix`` of one tag's corners (4, 2), finally in a window that stays inside the
    tag's black border cell (and, on an AprilGrid, inside the gap's corner square).

    On an AprilGrid the quad fit's corners can be off by more than that window: a first pass
    with a window of 1.5 cells brings them within reach, the second removes its bias."""
    side = float(np.mean(np.linalg.norm(q - np.roll(q, 1, axis=0), axis=1)))
    cell_px = side / _tag_cells(target)
    limit_px = cell_px
    if target.kind == "aprilgrid":
        limit_px = min(cell_px, side * target.tag_spacing)
    reach = 0.8 if target.kind == "aprilgrid" else TAG_SUBPIX_WINDOW_CELLS
    halves = [int(np.floor(reach * limit_px - 1.0))]
    if target.kind == "aprilgrid":
        halves.insert(0, int(np.floor(1.5 * cell_px)))
    c = q.astype(np.float32).reshape(-1, 1, 2)
    for half in halves:
        if half < _MIN_HALF_WINDOW_PX:
            break
        half = min(half, 15 if half == halves[-1] else 30)
        start = c.copy()
        c = cv2.cornerSubPix(grey, c, (half, half), (-1, -1), _SUBPIX_CRITERIA)
        if target.kind == "apriltag":  # an AprilGrid's corner squares bound its windows
            # the window reaches past a narrow paper margin: a corner that jumps is on the
            # paper's corner or the background's, not the tag's; it keeps where it was
            far = np.linalg.norm((c - start).reshape(4, 2), axis=1) > max(
                TAG_SUBPIX_JUMP_CELLS * cell_px, TAG_SUBPIX_JUMP_MIN_PX
            )
            c[far] = start[far]
    return np.asarray(c, dtype=np.float64).reshape(4, 2)


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
    if target.kind == "aprilgrid":
        cols = 2 * target.tag_cols
    elif target.kind in ("charuco", "chessboard"):
        cols = target.squares_x - 1
    else:
        return np.zeros(len(ids))  # no grid: a tag's 4 corners fix a homography exactly
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
    grey: np.ndarray,
    target: Target,
    ids: np.ndarray,
    px: np.ndarray,
    reasons: list[str],
    min_corners: int,
    path: str,
    stats: tuple[float, float, float],
) -> DetectionReport:
    shape = grey.shape
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
    min_corners = max(4, int(min_corners))
    if len(ids) < min_corners and (len(ids) or not reasons):
        msg = f"only {len(ids)} corners kept, fewer than min_corners={min_corners}"
        if len(rejected):
            msg += f" ({len(rejected)} rejected by the homography check)"
        reasons.append(msg)
    mean, saturated, blur = stats
    if not len(ids):
        if mean < DARK_MEAN_GREY:
            reasons.append(
                f"the image is too dark (mean grey {mean:.0f} of 255): more light or exposure"
            )
        if saturated > SATURATED_FRACTION:
            reasons.append(
                f"the image is saturated ({100 * saturated:.0f} % of pixels at 255): less "
                "exposure or gain, or move the glare off the board"
            )
        if blur > BLURRED_SIGMA_PX and mean >= DARK_MEAN_GREY:
            reasons.append(
                f"the image has no sharp edge (edge width {blur:.1f} px, a focused image of "
                "the board has < 1.5): the lens is out of focus at this distance, or nothing "
                "with edges is in view"
            )
    diagnosis = "; ".join(reasons)
    return DetectionReport(
        Detection(ids, px, diagnosis),
        ok=not reasons,
        reasons=tuple(reasons),
        homography_rms_px=rms,
        coverage=coverage,
        rejected_ids=rejected,
        path=path,
        blur_sigma_px=blur,
        saturated_fraction=saturated,
    )


# -- boards that look the same after a half turn -------------------------------------------------
#: A frame's half turn is decided when the other choice misses the rotations by this much more.
HALF_TURN_MARGIN_DEG = 20.0


def half_turn_symmetric(target: Target) -> bool:
    """Whether ``target`` looks the same after a half turn about its centre: a chessboard with
    both square counts even or both odd (its corner 0 cannot be read from one image)."""
    return target.kind == "chessboard" and (target.squares_x + target.squares_y) % 2 == 0


def half_turned(detection: Detection, target: Target) -> Detection:
    """``detection`` with the board's corner ids read after a half turn (corner ``i`` of the
    row-major grid becomes ``n - 1 - i``)."""
    return Detection(len(target.points_m) - 1 - detection.ids, detection.px, detection.reason)


def half_turn_T(target: Target) -> np.ndarray:
    """The board transform (4, 4) of a half turn about ``target``'s centre: board <- turned
    board (a pose ``T_cam_board`` read the other way round is ``T_cam_board @ half_turn_T``)."""
    c = target.points_m.mean(axis=0)
    return T_from_Rt(Rz(np.pi), np.array([2.0 * c[0], 2.0 * c[1], 0.0]))


def board_poses(
    problem: CalibrationProblem, cam: str, min_points: int = 4
) -> dict[int, np.ndarray]:
    """``T_cam_board`` (4, 4) of each frame (index) where ``cam`` saw ``min_points`` corners or
    more, from the images alone: OpenCV's pinhole calibration from a guess (f the image's long
    side, the principal point at its centre; one orientation's frames then keep equal
    rotations), then with the principal point and distortion free where that fits better; each
    frame's own PnP with the guess where OpenCV fails. A half turn changes no frame's
    intrinsics."""
    w, h = problem.camera(cam).width, problem.camera(cam).height
    K = np.array([[max(w, h), 0.0, (w - 1) / 2], [0.0, max(w, h), (h - 1) / 2], [0.0, 0.0, 1.0]])
    idx, obj, img = [], [], []
    for k, f in enumerate(problem.frames):
        d = f.detections.get(cam)
        if d is not None and len(d.ids) >= min_points:
            idx.append(k)
            obj.append(problem.target.points_m[d.ids].astype(np.float32))
            img.append(d.px.reshape(-1, 1, 2).astype(np.float32))
    flags = (
        cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_FIX_PRINCIPAL_POINT
        | cv2.CALIB_FIX_ASPECT_RATIO
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K1
        | cv2.CALIB_FIX_K2
        | cv2.CALIB_FIX_K3
    )
    try:
        rms, K, _, rvecs, tvecs = cv2.calibrateCamera(obj, img, (w, h), K, np.zeros(5), flags=flags)
        free = cv2.calibrateCamera(
            obj, img, (w, h), K, np.zeros(5), flags=cv2.CALIB_USE_INTRINSIC_GUESS
        )
        f = free[1][0, 0]  # a free focal length far from the guess: degenerate views
        if np.isfinite(free[0]) and free[0] < rms and 0.1 * max(w, h) < f < 10.0 * max(w, h):
            rvecs, tvecs = free[3], free[4]
    except cv2.error:
        pnp = [
            cv2.solvePnP(o, i, K, None, flags=cv2.SOLVEPNP_IPPE)
            for o, i in zip(obj, img, strict=True)
        ]
        rvecs, tvecs = [r[1] for r in pnp], [r[2] for r in pnp]
    return {
        k: T_from_Rt(R_from_rvec(np.reshape(r, 3)), np.reshape(t, 3))
        for k, r, t in zip(idx, rvecs, tvecs, strict=True)
    }


def angles_between_deg(R: np.ndarray | list[np.ndarray], turned: bool = False) -> np.ndarray:
    """(n, n) rotation angles (deg) of ``R_i' R_j`` for ``R`` (n, 3, 3), of ``R_i' R_j Rz(pi)``
    when ``turned`` (good to about 1e-6 deg near 0)."""
    rel = np.einsum("iba,jbc->ijac", np.asarray(R), np.asarray(R))
    trace = (-1.0 if turned else 1.0) * (rel[..., 0, 0] + rel[..., 1, 1]) + rel[..., 2, 2]
    return np.degrees(np.arccos(np.clip((trace - 1.0) / 2.0, -1.0, 1.0)))


def half_turns(
    R_cam_board: list[np.ndarray], R_base_tool: list[np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Which frames' board poses ``R_cam_board`` (n, 3, 3, images alone) are turned by half a
    turn about the board normal: the choice under which the angle of the camera's rotation
    between every two frames matches the robot's (``R_base_tool``, any mount: an angle does not
    depend on the hand-eye), or without a robot is smallest (continuity with the other frames).
    The fewer turns of the two equivalent answers. Returns (turned (n,) bool, margin (n,) deg:
    how much worse the other choice fits, median over the frame's pairs)."""
    n = len(R_cam_board)
    ref = 0.0 if R_base_tool is None else angles_between_deg(R_base_tool)
    cost = np.abs(np.stack([angles_between_deg(R_cam_board, t) for t in (False, True)]) - ref)
    others = ~np.eye(n, dtype=bool)

    def fit(i: int, s: np.ndarray) -> np.ndarray:  # median cost of frame i unturned, turned
        return np.array([np.median(cost[t ^ s, i, np.arange(n)][others[i]]) for t in (0, 1)])

    s = np.zeros(n, dtype=int)
    for _ in range(n):  # one frame at a time to the better choice, until none changes
        changed = False
        for i in range(n):
            best = int(np.argmin(fit(i, s)))
            changed |= best != s[i]
            s[i] = best
        if not changed:
            break
    if 2 * s.sum() > n:
        s = 1 - s
    margin = np.array([abs(float(np.diff(fit(i, s))[0])) for i in range(n)])
    return s.astype(bool), margin


def resolve_half_turns(problem: CalibrationProblem) -> tuple[CalibrationProblem, tuple[str, ...]]:
    """``problem`` with each frame of a board symmetric under a half turn read the right way
    round (:func:`half_turns`, by the robot's rotations, else by continuity), and a line per
    camera naming the frames turned. A frame neither choice fits better by
    ``HALF_TURN_MARGIN_DEG`` is refused (DegenerateError) when its turn matters: with robot poses,
    board-frame motions or a rig (one camera's frames alone each have their own board pose)."""
    target = problem.target
    if not half_turn_symmetric(target) or len(problem.frames) < 2:
        return problem, ()
    robot = problem.knowledge == "robot"
    matters = problem.knowledge != "none" or len(problem.cameras) > 1
    frames, notes = list(problem.frames), []
    for cam in problem.cameras:
        R = {k: T[:3, :3] for k, T in board_poses(problem, cam.name).items()}
        idx = list(R)
        if len(idx) < 2:
            continue
        tools = [problem.frames[k].T_base_tool[:3, :3] for k in idx] if robot else None
        turned, margin = half_turns([R[k] for k in idx], tools)
        sure = margin >= HALF_TURN_MARGIN_DEG
        unsure = [problem.frames[idx[a]].id for a in np.flatnonzero(~sure)]
        if unsure and matters:
            sx, sy = target.squares_x, target.squares_y
            raise DegenerateError(
                f"frames {unsure} {cam.name!r}: the {sx} x {sy}-square chessboard looks the same "
                "after a half turn, and neither way round fits "
                f"{'the robot rotations' if robot else 'the other frames'} better by "
                f"{HALF_TURN_MARGIN_DEG:.0f} deg: leave those frames out, or use a board with "
                f"one odd and one even count of squares (e.g. {sx + 1} x {sy})"
            )
        done = [idx[a] for a in np.flatnonzero(turned & sure)]
        for k in done:
            dets = dict(frames[k].detections)
            dets[cam.name] = half_turned(dets[cam.name], target)
            frames[k] = replace(frames[k], detections=dets)
        if done:
            notes.append(
                f"frames {[problem.frames[k].id for k in done]} {cam.name!r}: the chessboard looks "
                "the same after a half turn and was read the other way round there; turned back, "
                f"as {'the robot rotations between frames' if robot else 'the other frames'} "
                f"tell (the other way fits worse by {margin[turned & sure].min():.0f} deg or more)"
            )
    return replace(problem, frames=tuple(frames)), tuple(notes)

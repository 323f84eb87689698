"""Render what a simulated camera sees of a planar target (ray casting through the lens model).

For every pixel the renderer undistorts the pixel (``solver/camera.py``, so it agrees with
``project`` by construction), intersects the ray with the board plane and looks the board's
texture up there (inverse mapping). Anti-aliasing: ``n x n`` sub-samples per pixel at offsets
``(k + 0.5) / n - 0.5`` px from the pixel centre (pixel (0, 0) is the centre of the top-left
pixel), averaged (a sensor with 100 % fill factor). The texture is looked up with bilinear
interpolation at a resolution chosen per render so that one texel spans at least two
sub-samples' footprints on the board. Why: a texture much finer than the sub-samples would
quantise an edge's position in steps of ``1 / n`` px; with bilinear texels of width ``tau`` the
sum over sub-samples of the edge's ramp is exact when ``tau`` is a multiple of the sub-sample
spacing ``s`` and otherwise off by a periodic, zero-mean error of at most 0.028 px for
``tau / s`` in [1, 2] and 0.017 px for ``tau / s`` in [2, 3] (n = 3; computed, and checked on
rendered edges in ``tests/test_render.py``). The texture's own smoothing (a tent) is subtracted
from the optical blur, so the total blur stays ``blur_sigma_px`` where it can.

Then, in this order: optical blur (Gaussian, ``blur_sigma_px``), vignetting, exposure gain,
additive Gaussian read noise (``noise_std`` grey levels), clipping and quantisation to uint8.

Board appearance (board frame of ``solver/problem.py``: +z into the board, away from a camera
that reads the print): the print (ChArUco from OpenCV's own ``CharucoBoard.generateImage``, or a
chessboard whose square (0, 0) at the board origin is black) with a white margin of one square
all round. A camera on the +z side sees the back of the board: plain grey. Rays that miss the
board show a plain background grey.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import cv2
import numpy as np

from slidecal.solver.camera import project_with_jacobians, undistort_normalised
from slidecal.solver.detect import charuco_board
from slidecal.solver.errors import InputError
from slidecal.solver.problem import Target

if TYPE_CHECKING:
    from slidecal.mocks.camera import SimCamera

# Reflectances (fraction of full scale at exposure 1): printed black and white, the board's
# unprinted back, and the background behind the board.
BLACK = 0.06
WHITE = 0.85
BACK = 0.50
BACKGROUND = 0.35
SUBSAMPLES = 3  # n: n x n sub-samples per pixel
# Texture resolutions available (texels per square); a render picks the finest whose texel still
# spans TEXEL_FOOTPRINTS sub-sample footprints. Steps of about sqrt(2); at least 16 so that
# generateImage can draw a 5x5-bit marker with its border in a 22/30 square.
TEXELS_PER_SQUARE = (16, 23, 32, 45, 64, 90, 128, 181, 256)
TEXEL_FOOTPRINTS = 2.0
_OUTSIDE = -1.0e5  # texture coordinate of a ray that hits the plane behind the camera


def margin_m(target: Target) -> float:
    """Width of the white margin around the printed pattern, metres (one square)."""
    return target.square_size_m


@dataclass(frozen=True)
class _Texture:
    image: np.ndarray  # (h, w) float32, reflectance
    texels_per_m: float


def _check_target(target: Target) -> None:
    if target.kind not in ("charuco", "chessboard"):
        raise InputError(
            f"cannot render a target of kind {target.kind!r}; "
            "use a 'charuco' or 'chessboard' target"
        )
    if target.squares_x < 2 or target.squares_y < 2 or target.square_size_m <= 0.0:
        raise InputError("the target needs squares_x, squares_y >= 2 and square_size_m > 0")


@lru_cache(maxsize=8)
def _texture(
    kind: str,
    squares_x: int,
    squares_y: int,
    square_size_m: float,
    marker_size_m: float,
    dictionary: str,
    texels_per_square: int,
) -> _Texture:
    """The printed board with a margin of m texels: texel column j covers board x in
    [(j - m) / tpm, (j - m + 1) / tpm) (tpm texels per metre), likewise rows and y."""
    tps = texels_per_square
    m = tps  # margin in texels: one square
    w, h = squares_x * tps + 2 * m, squares_y * tps + 2 * m
    if kind == "charuco":
        board = charuco_board(
            Target.charuco(squares_x, squares_y, square_size_m, marker_size_m, dictionary)
        )
        img = board.generateImage((w, h), marginSize=m, borderBits=1)
        binary = img.astype(np.float32) / 255.0
    else:
        r, c = np.divmod(np.arange(h * w), w)
        sq_r, sq_c = (r - m) // tps, (c - m) // tps
        inside = (sq_r >= 0) & (sq_r < squares_y) & (sq_c >= 0) & (sq_c < squares_x)
        black = inside & ((sq_r + sq_c) % 2 == 0)
        binary = np.where(black, 0.0, 1.0).astype(np.float32).reshape(h, w)
    image = (BLACK + (WHITE - BLACK) * binary).astype(np.float32)
    return _Texture(image, tps / square_size_m)


@lru_cache(maxsize=4)
def _subsample_rays(
    width: int, height: int, K_bytes: bytes, dist_bytes: bytes, n: int
) -> np.ndarray:
    """Undistorted normalised coordinates (n H, n W, 2) float32 of every sub-sample of a camera.

    Exact undistortion at the pixel centres; the sub-samples, at most ``0.5 - 0.5 / n`` px away,
    use the local inverse Jacobian of the lens model (second-order error below 1e-4 px).
    """
    K = np.frombuffer(K_bytes).reshape(3, 3)
    dist = np.frombuffer(dist_bytes)
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    xy = undistort_normalised(K, dist, px)
    J = project_with_jacobians(K, dist, np.column_stack([xy, np.ones(len(xy))])).d_P[:, :, :2]
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    Jinv = np.stack(
        [J[:, 1, 1] / det, -J[:, 0, 1] / det, -J[:, 1, 0] / det, J[:, 0, 0] / det], axis=1
    ).reshape(height, width, 2, 2)
    xy = xy.reshape(height, width, 2)
    off = (np.arange(n) + 0.5) / n - 0.5
    rays = np.empty((height, n, width, n, 2), dtype=np.float32)
    for a, dv in enumerate(off):
        for b, du in enumerate(off):
            d = np.array([du, dv])
            rays[:, a, :, b, :] = xy + Jinv @ d
    return rays.reshape(height * n, width * n, 2)


def _rays(cam: SimCamera, n: int) -> np.ndarray:
    K = np.ascontiguousarray(cam.K, dtype=float)
    dist = np.zeros(5)
    dd = np.asarray(cam.dist, dtype=float).reshape(-1)
    dist[: min(5, len(dd))] = dd[:5]
    return _subsample_rays(int(cam.width), int(cam.height), K.tobytes(), dist.tobytes(), n)


def _footprint_m(cam: SimCamera, target: Target, T_cam_board: np.ndarray, n: int) -> float:
    """Largest sub-sample footprint (metres on the board) over the board's visible part."""
    sx, sy, sq = target.squares_x, target.squares_y, target.square_size_m
    gx, gy = np.meshgrid(np.linspace(0.0, sx * sq, 7), np.linspace(0.0, sy * sq, 7))
    P_board = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    R, t = T_cam_board[:3, :3], T_cam_board[:3, 3]
    P_cam = P_board @ R.T + t
    front = P_cam[:, 2] > 1e-6
    if not np.any(front):
        return np.inf
    pr = project_with_jacobians(np.asarray(cam.K, float), np.asarray(cam.dist, float), P_cam[front])
    J = pr.d_P @ R[:, :2]  # d px / d (X, Y) board, (m, 2, 2)
    inside = (
        (pr.px[:, 0] > -0.5)
        & (pr.px[:, 0] < cam.width - 0.5)
        & (pr.px[:, 1] > -0.5)
        & (pr.px[:, 1] < cam.height - 0.5)
    )
    if np.any(inside):
        J = J[inside]
    s_min = np.linalg.svd(J, compute_uv=False)[:, -1]  # px per metre, worst direction
    return float(np.max(1.0 / np.maximum(s_min, 1e-12))) / n


def render_target(
    target: Target,
    cam: SimCamera,
    T_cam_board: np.ndarray,
    rng: np.random.Generator,
    *,
    vignetting: float = 0.0,
) -> np.ndarray:
    """The image camera ``cam`` takes of ``target`` at pose ``T_cam_board``.

    Parameters
    ----------
    target
        A ``charuco`` or ``chessboard`` target (board frame and ids of ``solver/problem.py``).
    cam
        The simulated camera (``SimCamera``: size, ``K`` (3, 3) px, ``dist`` (5,), blur, noise,
        exposure, colour).
    T_cam_board
        (4, 4) board frame to camera frame, metres.
    rng
        Source of the read noise.
    vignetting
        Relative fall-off at the image corners (0: none; 0.3: corners 30 % darker), quadratic in
        the distance from the principal point.

    Returns
    -------
    np.ndarray
        uint8 (H, W), or (H, W, 3) BGR when ``cam.colour``.
    """
    _check_target(target)
    T = np.asarray(T_cam_board, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError("T_cam_board must be a finite 4x4 transform (board frame to camera)")
    n = SUBSAMPLES
    texture_sigma_px = 0.0
    W, H = int(cam.width), int(cam.height)
    R, t = T[:3, :3], T[:3, 3]
    normal_cam = R[:, 2]  # board +z in camera axes
    rays = _rays(cam, n)
    # Board plane seen from the front (print side) when the camera centre has z_board < 0,
    # i.e. normal . t > 0 (camera centre in board frame is -R^T t).
    front = float(normal_cam @ t) > 0.0
    M = np.column_stack([R[:, 0], R[:, 1], t])  # x ~ M (X, Y, 1)
    if abs(np.linalg.det(M)) < 1e-15:  # camera centre on the board plane: sees the edge only
        hi = np.full((H * n, W * n), BACKGROUND, np.float32)
    else:
        G = np.linalg.inv(M)  # (X, Y, 1) / s = G (x, y, 1), s > 0 for a hit in front of the camera
        mg = margin_m(target)
        if front:
            footprint = _footprint_m(cam, target, T, n)
            tps = _pick_texels_per_square(target, TEXEL_FOOTPRINTS * footprint)
            if np.isfinite(footprint):
                # bilinear tent of half-width one texel, in pixels: std texel / sqrt(6)
                texel_px = target.square_size_m / tps / (footprint * n)
                texture_sigma_px = texel_px / np.sqrt(6.0)
            tex = _texture(
                target.kind,
                target.squares_x,
                target.squares_y,
                target.square_size_m,
                target.marker_size_m,
                target.dictionary,
                tps,
            )
            image, tpm = tex.image, tex.texels_per_m
        else:
            tpm = 8.0 / target.square_size_m
            h = int(round((target.squares_y * target.square_size_m + 2 * mg) * tpm))
            w = int(round((target.squares_x * target.square_size_m + 2 * mg) * tpm))
            image = np.full((h, w), BACK, np.float32)
        # board metres -> texture coordinates (texel centres at integers, cv2.remap convention)
        S = np.array([[tpm, 0.0, mg * tpm - 0.5], [0.0, tpm, mg * tpm - 0.5], [0.0, 0.0, 1.0]])
        A = S @ G
        w_h = cv2.transform(rays, G[2:3, :].astype(np.float64))  # 1 / s, (nH, nW, 1)
        uv = cv2.perspectiveTransform(rays, A)
        uv[w_h[..., 0] <= 0.0] = _OUTSIDE
        hi = cv2.remap(
            image,
            uv,
            None,
            interpolation=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=BACKGROUND,
        )
    img = cv2.resize(hi, (W, H), interpolation=cv2.INTER_AREA)  # exact n x n box average
    blur_px = float(np.sqrt(max(cam.blur_sigma_px**2 - texture_sigma_px**2, 0.0)))
    return _sensor(img, cam, rng, vignetting, blur_px)


def _pick_texels_per_square(target: Target, texel_min_m: float) -> int:
    """The finest texture level whose texel is at least ``texel_min_m``."""
    if not np.isfinite(texel_min_m):
        return TEXELS_PER_SQUARE[0]
    best = TEXELS_PER_SQUARE[0]
    for tps in TEXELS_PER_SQUARE:
        if target.square_size_m / tps >= texel_min_m:
            best = tps
    return best


def _sensor(
    img: np.ndarray, cam: SimCamera, rng: np.random.Generator, vignetting: float, blur_px: float
) -> np.ndarray:
    """Blur, vignetting, exposure, read noise, clipping and quantisation of a (H, W) image."""
    H, W = img.shape
    if blur_px > 0.0:
        img = cv2.GaussianBlur(img, (0, 0), sigmaX=blur_px, borderType=cv2.BORDER_REPLICATE)
    gain = 255.0 * cam.exposure
    if vignetting > 0.0:
        K = np.asarray(cam.K, float)
        u = (np.arange(W, dtype=np.float32) - K[0, 2]) / max(K[0, 2], W - K[0, 2])
        v = (np.arange(H, dtype=np.float32) - K[1, 2]) / max(K[1, 2], H - K[1, 2])
        r2 = (u[None, :] ** 2 + v[:, None] ** 2) / 2.0
        img = img * (1.0 - vignetting * r2)
    signal = img * np.float32(gain)
    channels = 3 if cam.colour else 1
    out = []
    for _ in range(channels):
        noisy = signal
        if cam.noise_std > 0.0:
            noisy = signal + rng.standard_normal((H, W), dtype=np.float32) * np.float32(
                cam.noise_std
            )
        out.append(np.clip(np.rint(noisy), 0, 255).astype(np.uint8))
    return out[0] if channels == 1 else np.stack(out, axis=2)

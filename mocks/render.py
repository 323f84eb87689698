"""Render what a simulated camera sees of a planar target (ray casting through the lens model
of ``solver/camera.py``, so it agrees with ``project``), optionally photograph-like
(:class:`Photo`). Sampling, blur, noise and the board's appearance: docs/DRIVERS.md."""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import TYPE_CHECKING

import cv2
import numpy as np

from slidecal.solver.camera import (
    as_distortion,
    distortion_jacobian,
    project_with_jacobians,
    undistort_normalised,
)
from slidecal.solver.detect import charuco_board
from slidecal.solver.errors import InputError
from slidecal.solver.problem import Target
from slidecal.solver.target_shape import bow_height_m

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
DEFAULT_TAGS = "DICT_APRILTAG_36h11"  # a tag target's dictionary when it names none


def margin_m(target: Target) -> float:
    """Width of the white margin around the printed pattern, metres."""
    if target.kind in ("apriltag", "aprilgrid"):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, target.dictionary))
        return _tag_margin_m(target, d.markerSize + 2)
    return target.square_size_m


def _tag_margin_m(tag: Target, cells: int) -> float:
    """A tag print's white margin, metres: one cell of a lone tag (``cells`` across it), as a
    tag is printed from its family's images; a quarter of a tag beyond an AprilGrid's outer
    corner squares (``tag_spacing`` of a tag wide)."""
    if tag.kind == "aprilgrid":
        return (0.25 + tag.tag_spacing) * tag.tag_size_m
    return tag.tag_size_m / cells


def unit_m(target: Target) -> float:
    """The print's unit (a square, or a tag): texture resolutions are texels per unit."""
    return target.tag_size_m if target.kind in ("apriltag", "aprilgrid") else target.square_size_m


def extent_m(target: Target) -> tuple[float, float]:
    """Width and height (metres) of the printed pattern, from the board origin, margin excluded."""
    if target.kind in ("charuco", "chessboard"):
        return target.squares_x * target.square_size_m, target.squares_y * target.square_size_m
    xy = target.points_m[:, :2]
    return float(xy[:, 0].max()), float(xy[:, 1].max())


@dataclass(frozen=True)
class _Texture:
    image: np.ndarray  # (h, w) float32, reflectance
    texels_per_m: float


def _check_target(target: Target) -> None:
    kinds = ("charuco", "chessboard", "apriltag", "aprilgrid")
    if target.kind not in kinds:
        raise InputError(
            f"cannot render a target of kind {target.kind!r}; use one of {', '.join(kinds)}"
        )
    if target.kind in ("apriltag", "aprilgrid"):
        if target.tag_size_m <= 0.0:
            raise InputError("a tag target needs tag_size_m > 0")
        return
    if target.squares_x < 2 or target.squares_y < 2 or target.square_size_m <= 0.0:
        raise InputError("the target needs squares_x, squares_y >= 2 and square_size_m > 0")


def _texture_of(target: Target, texels_per_unit: int) -> _Texture:
    """The print's texture, cached by its description (of its points only a tag set's places)."""
    printed = replace(target, points_m=None)  # hashable
    if target.kind == "aprilgrid":
        return _tag_texture(printed, (), texels_per_unit)
    if target.kind == "apriltag":
        origins = tuple(map(tuple, np.round(target.points_m[::4, :2], 12)))
        return _tag_texture(printed, origins, texels_per_unit)
    return _texture(printed, texels_per_unit)


@lru_cache(maxsize=8)
def _tag_texture(
    tag: Target, tag_origins_m: tuple[tuple[float, float], ...], texels_per_tag: int
) -> _Texture:
    kind, tag_ids, tag_cols, tag_rows = tag.kind, tag.tag_ids, tag.tag_cols, tag.tag_rows
    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, tag.dictionary or DEFAULT_TAGS))
    cells = d.markerSize + 2
    s = tag.tag_size_m
    tpm = texels_per_tag / s
    gap = tag.tag_spacing * s
    mg = _tag_margin_m(tag, cells)
    if kind == "aprilgrid":
        pitch = s + gap
        width, height = tag_cols * pitch - gap, tag_rows * pitch - gap
        # tag t sits at tag row i = t // cols counted from the bottom (Kalibr), column k
        origins = [
            ((t % tag_cols) * pitch, (tag_rows - 1 - t // tag_cols) * pitch) for t in tag_ids
        ]
    else:
        pitch = 0.0
        origins = list(tag_origins_m)
        width = max(o[0] for o in origins) + s
        height = max(o[1] for o in origins) + s
    w = int(np.ceil((width + 2 * mg) * tpm))
    h = int(np.ceil((height + 2 * mg) * tpm))
    steps = np.arange(cells + 1) * (s / cells)
    xb = [np.array([-mg, w / tpm - mg])] + [x0 + steps for x0, _ in origins]
    yb = [np.array([-mg, h / tpm - mg])] + [y0 + steps for _, y0 in origins]
    if kind == "aprilgrid":
        xb += [np.arange(tag_cols + 1) * pitch - gap, np.arange(tag_cols + 1) * pitch]
        yb += [np.arange(tag_rows + 1) * pitch - gap, np.arange(tag_rows + 1) * pitch]
    xb = np.unique(np.clip(np.concatenate(xb), -mg, w / tpm - mg))
    yb = np.unique(np.clip(np.concatenate(yb), -mg, h / tpm - mg))
    # value of every rectangle between consecutive edges, at its centre
    X, Y = np.meshgrid(0.5 * (xb[:-1] + xb[1:]), 0.5 * (yb[:-1] + yb[1:]))
    val = np.ones(X.shape)
    for t, (x0, y0) in zip(tag_ids, origins, strict=True):
        bits = cv2.aruco.generateImageMarker(d, int(t), cells, borderBits=1)
        u = np.floor((X - x0) / s * cells).astype(int)
        v = np.floor((Y - y0) / s * cells).astype(int)
        inside = (u >= 0) & (u < cells) & (v >= 0) & (v < cells)
        val[inside] = bits[v[inside], u[inside]] / 255.0
    if kind == "aprilgrid":
        # Kalibr's corner squares: side gap, in the gaps at every tag corner
        gx, gy = np.floor((X + gap) / pitch), np.floor((Y + gap) / pitch)
        fx, fy = X + gap - gx * pitch, Y + gap - gy * pitch
        sq = (fx < gap) & (fy < gap) & (gx >= 0) & (gx <= tag_cols) & (gy >= 0) & (gy <= tag_rows)
        val[sq] = 0.0

    def coverage(edges: np.ndarray, n: int) -> np.ndarray:
        """(n, m) fraction of texel j inside the interval [edges[i], edges[i + 1])."""
        t0 = np.arange(n) / tpm - mg
        lo = np.maximum(t0[:, None], edges[None, :-1])
        hi = np.minimum(t0[:, None] + 1.0 / tpm, edges[None, 1:])
        return np.clip(hi - lo, 0.0, None) * tpm

    binary = coverage(yb, h) @ val @ coverage(xb, w).T
    image = (BLACK + (WHITE - BLACK) * binary).astype(np.float32)
    return _Texture(image, tpm)


@lru_cache(maxsize=8)
def _texture(board: Target, texels_per_square: int) -> _Texture:
    """The printed board with a margin of m texels: texel column j covers board x in
    [(j - m) / tpm, (j - m + 1) / tpm) (tpm texels per metre), likewise rows and y."""
    tps = texels_per_square
    m = tps  # margin in texels: one square
    squares_x, squares_y = board.squares_x, board.squares_y
    w, h = squares_x * tps + 2 * m, squares_y * tps + 2 * m
    if board.kind == "charuco":
        img = charuco_board(board).generateImage((w, h), marginSize=m, borderBits=1)
        binary = img.astype(np.float32) / 255.0
    else:
        r, c = np.divmod(np.arange(h * w), w)
        sq_r, sq_c = (r - m) // tps, (c - m) // tps
        inside = (sq_r >= 0) & (sq_r < squares_y) & (sq_c >= 0) & (sq_c < squares_x)
        black = inside & ((sq_r + sq_c) % 2 == 0)
        binary = np.where(black, 0.0, 1.0).astype(np.float32).reshape(h, w)
    image = (BLACK + (WHITE - BLACK) * binary).astype(np.float32)
    return _Texture(image, tps / board.square_size_m)


@lru_cache(maxsize=4)
def _subsample_rays(
    width: int, height: int, K_bytes: bytes, dist_bytes: bytes, n: int
) -> np.ndarray:
    """Undistorted normalised coordinates (n H, n W, 2) float32 of every sub-sample of a camera:
    exact at the pixel centres, by the lens model's local inverse Jacobian around them."""
    K = np.frombuffer(K_bytes).reshape(3, 3)
    dist = np.frombuffer(dist_bytes)
    u, v = np.meshgrid(np.arange(width, dtype=float), np.arange(height, dtype=float))
    px = np.stack([u.ravel(), v.ravel()], axis=1)
    xy = undistort_normalised(K, dist, px)
    Jinv = np.linalg.inv(distortion_jacobian(K, dist, xy)[1]).reshape(height, width, 2, 2)
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
    dist = as_distortion(cam.dist)
    return _subsample_rays(int(cam.width), int(cam.height), K.tobytes(), dist.tobytes(), n)


def _footprint_m(cam: SimCamera, target: Target, T_cam_board: np.ndarray, n: int) -> float:
    """Largest sub-sample footprint (metres on the board) over the board's visible part."""
    ex, ey = extent_m(target)
    gx, gy = np.meshgrid(np.linspace(0.0, ex, 7), np.linspace(0.0, ey, 7))
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
    photo: Photo | None = None,
    bow_m: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """The image camera ``cam`` (``SimCamera``) takes of ``target`` (charuco or chessboard) at
    ``T_cam_board`` (4, 4), metres: uint8 (H, W), or (H, W, 3) BGR when ``cam.colour``.

    ``rng``: the read noise. ``vignetting``: relative fall-off at the image corners, quadratic in
    the distance from the principal point. ``photo``: :class:`Photo` (None: ``cam.photo``, None
    there too: the clean renderer). ``bow_m``: the board's bow along x and y (metres,
    ``solver/target_shape.py``'s modes; (0, 0): flat).
    """
    _check_target(target)
    T = np.asarray(T_cam_board, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError("T_cam_board must be a finite 4x4 transform (board frame to camera)")
    photo = photo if photo is not None else getattr(cam, "photo", None)
    n = SUBSAMPLES
    texture_sigma_px = 0.0
    inv_depth = None  # (nH, nW) 1 / z of the board along every sub-sample ray
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
        inv_depth = np.zeros((H * n, W * n), np.float32)
    else:
        G = np.linalg.inv(M)  # (X, Y, 1) / s = G (x, y, 1), s > 0 for a hit in front of the camera
        mg = margin_m(target)
        if front:
            footprint = _footprint_m(cam, target, T, n)
            tps = _pick_texels_per_square(target, TEXEL_FOOTPRINTS * footprint)
            if np.isfinite(footprint):
                # bilinear tent of half-width one texel, in pixels: std texel / sqrt(6)
                texel_px = unit_m(target) / tps / (footprint * n)
                texture_sigma_px = texel_px / np.sqrt(6.0)
            tex = _texture_of(target, tps)
            image, tpm = tex.image, tex.texels_per_m
        else:
            tpm = 8.0 / unit_m(target)
            ex, ey = extent_m(target)
            h = int(round((ey + 2 * mg) * tpm))
            w = int(round((ex + 2 * mg) * tpm))
            image = np.full((h, w), BACK, np.float32)
        # board metres -> texture coordinates (texel centres at integers, cv2.remap convention)
        S = np.array([[tpm, 0.0, mg * tpm - 0.5], [0.0, tpm, mg * tpm - 0.5], [0.0, 0.0, 1.0]])
        w_h = cv2.transform(rays, G[2:3, :].astype(np.float64))  # 1 / s, (nH, nW)
        inv_depth = np.maximum(w_h, 0.0)
        if bow_m[0] or bow_m[1]:
            xy, inv_depth = _bowed_hits(target, np.asarray(bow_m, float), rays, G, R[:, 2], w_h)
            uv = (xy @ S[:2, :2].T + S[:2, 2]).astype(np.float32)
        else:
            uv = cv2.perspectiveTransform(rays, S @ G)
        uv[w_h <= 0.0] = _OUTSIDE  # behind the camera: past the board plane's horizon
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
    if photo is None:
        return _sensor(img, cam, rng, vignetting, blur_px)
    inv_z = cv2.resize(
        np.ascontiguousarray(inv_depth.reshape(H * n, W * n)), (W, H), interpolation=cv2.INTER_AREA
    )
    return _photo(img, inv_z, cam, photo, rng, texture_sigma_px)


def _bowed_hits(
    target: Target,
    bow_m: np.ndarray,
    rays: np.ndarray,
    G: np.ndarray,
    z_axis_cam: np.ndarray,
    w_h: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Board coordinates (nH, nW, 2) where each ray meets the bowed board, and 1 / depth there.

    A point ``(X, Y, z)`` of the board is ``M (X, Y, 1) + z r3`` in the camera (``M = [r1 r2
    t]``, ``G = M^-1``); on the ray ``s x`` that gives ``(X, Y) = (X0, Y0) + z (g3 (X0, Y0) -
    (g1, g2))`` and ``1 / s = w / (1 + z g3)``, ``(X0, Y0)`` the plane's hit, ``w = (G x)_3``,
    ``g = G r3``.
    """
    g = G @ z_axis_cam
    XY0 = cv2.perspectiveTransform(rays, G).astype(np.float64)
    XY = XY0
    z = np.zeros(XY.shape[:2])
    for _ in range(2):
        z = bow_height_m(target, bow_m, XY[..., 0], XY[..., 1])
        XY = XY0 + z[..., None] * (g[2] * XY0 - g[:2])
    return XY, np.maximum(w_h / (1.0 + z * g[2]), 0.0).astype(np.float32)


def _pick_texels_per_square(target: Target, texel_min_m: float) -> int:
    """The finest texture level whose texel is at least ``texel_min_m``."""
    fine_enough = [tps for tps in TEXELS_PER_SQUARE if unit_m(target) / tps >= texel_min_m]
    return fine_enough[-1] if fine_enough else TEXELS_PER_SQUARE[0]


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


@dataclass(frozen=True)
class Photo:
    """Photograph-like imaging; the defaults are an industrial colour camera with a fixed-focus lens
    at f/4 under workshop light. The fields, their units and defaults: docs/FORMATS.md (``photo``).
    """

    aperture_mm: float = 2.0
    focus_distance_m: float | None = None
    pixel_pitch_um: float = 3.0
    chromatic_red: float = 5e-4
    chromatic_blue: float = -5e-4
    full_well_e: float = 8000.0
    bayer: bool = True
    jpeg_quality: int = 90
    vignetting: float = 0.3
    gradient: float = 0.2
    glare_spots: int = 1
    glare_strength: float = 0.5
    glare_radius: float = 0.04

    def __post_init__(self) -> None:
        if not 0 <= self.jpeg_quality <= 100:
            raise InputError(f"jpeg_quality must be 0 (none) or 1..100, got {self.jpeg_quality}")
        if min(self.aperture_mm, self.pixel_pitch_um, self.full_well_e, self.glare_radius) < 0:
            raise InputError("aperture_mm, pixel_pitch_um, full_well_e, glare_radius must be >= 0")


def defocus_sigma_px(photo: Photo, f_px: float, inv_z: np.ndarray, inv_focus: float) -> np.ndarray:
    """Gaussian std (px) of the defocus blur at inverse depths ``inv_z`` (1/m): a quarter of the
    thin-lens blur circle diameter ``f_px * aperture * |1/z - 1/z_focus|``."""
    return 0.25 * f_px * photo.aperture_mm * 1e-3 * np.abs(inv_z - inv_focus)


def _varying_blur(img: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Blur with a per-pixel Gaussian std: blurred copies at a ladder of stds, interpolated."""
    top = float(np.max(sigma))
    if top <= 0.05:
        return img
    levels = [0.0]
    while levels[-1] < top:
        levels.append(max(0.5, levels[-1] * 1.5))
    copies = [img] + [
        cv2.GaussianBlur(img, (0, 0), sigmaX=lv, borderType=cv2.BORDER_REPLICATE)
        for lv in levels[1:]
    ]
    lv = np.asarray(levels)
    k = np.clip(np.searchsorted(lv, sigma, side="right") - 1, 0, len(lv) - 2)
    t = np.clip((sigma - lv[k]) / (lv[k + 1] - lv[k]), 0.0, 1.0).astype(np.float32)
    out = np.empty_like(img)
    for i in range(len(lv) - 1):
        sel = k == i
        if np.any(sel):
            out[sel] = (1.0 - t[sel]) * copies[i][sel] + t[sel] * copies[i + 1][sel]
    return out


def _radial_scale(img: np.ndarray, K: np.ndarray, scale: float) -> np.ndarray:
    """The image magnified by ``1 + scale`` about the principal point (bilinear)."""
    if scale == 0.0:
        return img
    H, W = img.shape
    cx, cy = float(K[0, 2]), float(K[1, 2])
    u = np.arange(W, dtype=np.float32)[None, :]
    v = np.arange(H, dtype=np.float32)[:, None]
    mx = (cx + (u - cx) / (1.0 + scale)).astype(np.float32) + np.zeros((H, 1), np.float32)
    my = (cy + (v - cy) / (1.0 + scale)).astype(np.float32) + np.zeros((1, W), np.float32)
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _photo(
    img: np.ndarray,
    inv_z: np.ndarray,
    cam: SimCamera,
    photo: Photo,
    rng: np.random.Generator,
    texture_sigma_px: float,
) -> np.ndarray:
    """Light, optics, sensor and compression of a (H, W) reflectance image (see ``Photo``)."""
    H, W = img.shape
    K = np.asarray(cam.K, float)
    # light: vignetting, a gradient, glare (before the optics: they blur with the board)
    u = (np.arange(W, dtype=np.float32) - K[0, 2]) / max(K[0, 2], W - K[0, 2])
    v = (np.arange(H, dtype=np.float32) - K[1, 2]) / max(K[1, 2], H - K[1, 2])
    light = 1.0 - photo.vignetting * (u[None, :] ** 2 + v[:, None] ** 2) / 2.0
    angle = rng.uniform(0.0, 2.0 * np.pi)
    ramp = (np.cos(angle) * u[None, :] + np.sin(angle) * v[:, None]) / 2.0
    light = light * (1.0 + photo.gradient * ramp)
    img = img * light.astype(np.float32)
    if photo.glare_spots > 0 and photo.glare_strength > 0.0:
        radius = photo.glare_radius * float(np.hypot(W, H))
        for _ in range(photo.glare_spots):
            x0, y0 = rng.uniform(0.25, 0.75) * W, rng.uniform(0.25, 0.75) * H
            g = np.exp(
                -0.5
                * ((np.arange(W) - x0)[None, :] ** 2 + (np.arange(H) - y0)[:, None] ** 2)
                / radius**2
            )
            img = img + np.float32(photo.glare_strength / cam.exposure) * g.astype(np.float32)
    # optics: the camera's blur (less the texture's own) and the defocus
    base = max(cam.blur_sigma_px**2 - texture_sigma_px**2, 0.0)
    f_px = float(K[0, 0])
    if photo.aperture_mm > 0.0:
        hit = inv_z > 0.0
        if photo.focus_distance_m is not None:
            inv_focus = 1.0 / photo.focus_distance_m
        elif np.any(hit):
            inv_focus = 1.0 / (1.1 / float(inv_z[hit].max()))
        else:
            inv_focus = 0.0
        z_inv = np.where(hit, inv_z, 0.0)  # background: at infinity
        defocus = defocus_sigma_px(photo, f_px, z_inv, inv_focus)
    else:
        defocus = np.zeros((H, W))
    sigma = np.sqrt(base + defocus**2).astype(np.float32)
    img = _varying_blur(np.ascontiguousarray(img, dtype=np.float32), sigma)
    # lateral chromatic aberration: red and blue magnified against green
    gain = np.float32(255.0 * cam.exposure)
    if cam.colour:
        bgr = [
            _radial_scale(img, K, photo.chromatic_blue),
            img,
            _radial_scale(img, K, photo.chromatic_red),
        ]
        signal = [c * gain for c in bgr]
    else:
        signal = [img * gain]

    # sensor: shot noise (electrons), read noise (grey levels), quantisation
    def expose(x: np.ndarray) -> np.ndarray:
        x = np.maximum(x, 0.0)
        if photo.full_well_e > 0.0:
            e_per_dn = photo.full_well_e / 255.0
            x = x + np.sqrt(x / e_per_dn) * rng.standard_normal(x.shape, dtype=np.float32)
        if cam.noise_std > 0.0:
            x = x + np.float32(cam.noise_std) * rng.standard_normal(x.shape, dtype=np.float32)
        return np.clip(np.rint(x), 0, 255).astype(np.uint8)

    if cam.colour and photo.bayer:
        mosaic = np.empty((H, W), np.float32)
        b, g, r = signal
        mosaic[0::2, 0::2] = r[0::2, 0::2]
        mosaic[0::2, 1::2] = g[0::2, 1::2]
        mosaic[1::2, 0::2] = g[1::2, 0::2]
        mosaic[1::2, 1::2] = b[1::2, 1::2]
        out = cv2.cvtColor(expose(mosaic), cv2.COLOR_BayerRGGB2BGR_EA)
    elif cam.colour:
        out = np.stack([expose(c) for c in signal], axis=2)
    else:
        out = expose(signal[0])
    if photo.jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(photo.jpeg_quality)])
        if ok:
            out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return out

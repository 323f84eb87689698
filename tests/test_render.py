"""The target renderer and the simulated camera rig, against the lens model's ground truth."""

import time
from dataclasses import replace

import cv2
import numpy as np
import pytest

from slidecal.mocks import render
from slidecal.mocks.camera import (
    SimCamera,
    SimulatedCameraRig,
    oak_d_like,
    oak_d_like_extrinsics,
    single_camera,
)
from slidecal.solver.camera import K_matrix, project
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import Rx, Ry, Rz, T_from_Rt
from slidecal.solver.problem import Target

SMALL = SimCamera("small", 320, 240, K_matrix(400.0, 400.0, 160.0, 120.0), np.zeros(5))


def _facing(target, dist_m, shift_m=(0.0, 0.0), R=None):
    """T_cam_board (4, 4): board centre at (shift, dist) in the camera, print towards it."""
    R = np.eye(3) if R is None else R
    c = np.array([target.squares_x, target.squares_y, 0.0]) * target.square_size_m / 2
    return T_from_Rt(R, np.array([shift_m[0], shift_m[1], dist_m]) - R @ c)


@pytest.mark.parametrize("shift_px", [0.0, 0.23, 0.5, 0.71])
def test_edge_position_by_area_is_exact(shift_px):
    # Detector-free check of the pixel convention and the sub-sample offsets: across a vertical
    # black/white edge the sum of the white fractions of a row of pixels equals the edge's
    # position minus the left border of the row's first pixel (area conservation).
    tg = Target.chessboard(7, 6, 0.03)
    cam = replace(SMALL, blur_sigma_px=0.0, noise_std=0.0)
    z = 0.6
    T = _facing(tg, z, (shift_px * z / 400.0, 0.0))
    img = render.render_target(tg, cam, T, np.random.default_rng(0)).astype(float)
    lo, hi = render.BLACK * 255, render.WHITE * 255
    # edge between columns 2 and 3 of squares, at board X = 3 squares; row 1 of squares
    edge_u = project(cam.K, None, (np.array([[0.09, 0.045, 0.0]]) @ T[:3, :3].T + T[:3, 3]))[0]
    v = int(round(edge_u[1]))
    a = int(np.floor(edge_u[0])) - 8
    row = img[v, a : a + 17]
    white_left = (row[0] - lo) > (hi - row[0])
    frac = (row - lo) / (hi - lo)
    if not white_left:
        frac = 1.0 - frac
    e = a - 0.5 + frac.sum()
    # residual sources: uint8 quantisation (<= 0.0025 px per partly covered pixel, three of
    # them) and the texture's bilinear ramp sampled by 3 sub-samples (<= 0.017 px at the 2.6
    # sub-samples per texel used here, see mocks/render.py); a wrong sub-sample offset or
    # pixel-centre convention would be >= 1/6 px
    assert abs(e - edge_u[0]) < 0.03


def test_corners_agree_with_the_lens_model():
    # Distorted R1 camera, noise-free, tilted: cornerSubPix started at the projected truth must
    # stay on it (cornerSubPix's own pixel-locking error is ~0.05 px rms, zero-mean).
    tg = Target.chessboard(11, 8, 0.03)
    cam = replace(single_camera(), noise_std=0.0)
    T = _facing(tg, 0.45, (0.05, 0.03), Rx(np.radians(25)) @ Ry(np.radians(-20)))
    img = render.render_target(tg, cam, T, np.random.default_rng(1))
    truth = project(cam.K, cam.dist, tg.points_m @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    ref = cv2.cornerSubPix(img, truth.reshape(-1, 1, 2).copy(), (5, 5), (-1, -1), crit)
    e = ref.reshape(-1, 2) - truth
    rms = float(np.sqrt(np.mean(np.sum(e * e, axis=1))))
    assert rms < 0.08
    assert np.all(np.abs(e.mean(axis=0)) < 0.02)


@pytest.mark.slow
def test_a_bowed_board_is_drawn_where_its_bowed_corners_project():
    # the R1 camera, noise-free, tilted, a board bowed by 3 mm along x and -2 mm along y
    # (exaggerated tenfold so the bow moves corners by pixels): cornerSubPix stays on the
    # projection of the bowed corners (solver/target_shape.py's modes) and off the flat ones
    from slidecal.solver.target_shape import shape_modes

    tg = Target.chessboard(11, 8, 0.03)
    cam = replace(single_camera(), noise_std=0.0)
    T = _facing(tg, 0.45, (0.05, 0.03), Rx(np.radians(25)) @ Ry(np.radians(-20)))
    bow = (3e-3, -2e-3)
    modes = shape_modes(tg, tg.points_m)
    bowed = tg.points_m + bow[0] * modes[3] + bow[1] * modes[4]
    img = render.render_target(tg, cam, T, np.random.default_rng(1), bow_m=bow)
    truth = project(cam.K, cam.dist, bowed @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
    flat = project(cam.K, cam.dist, tg.points_m @ T[:3, :3].T + T[:3, 3])
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    ref = cv2.cornerSubPix(img, truth.reshape(-1, 1, 2).copy(), (5, 5), (-1, -1), crit)
    e = ref.reshape(-1, 2) - truth
    assert float(np.sqrt(np.mean(np.sum(e * e, axis=1)))) < 0.08
    assert np.all(np.abs(e.mean(axis=0)) < 0.02)
    assert np.max(np.linalg.norm(truth - flat, axis=1)) > 1.0
    # no bow: the flat renderer, bit for bit
    a = render.render_target(tg, cam, T, np.random.default_rng(2))
    b = render.render_target(tg, cam, T, np.random.default_rng(2), bow_m=(0.0, 0.0))
    assert np.array_equal(a, b)


def test_nothing_is_drawn_past_the_board_planes_horizon():
    # a camera 0.3 m above the middle of a 4 m board, looking at it at a grazing 10 deg and
    # rolled 30 deg: the plane's horizon crosses the image diagonally. Every pixel whose ray
    # points away from the plane is background, though the ray's backward extension meets the
    # board behind the camera for 2889 of them (the renderer once masked such rays row by row,
    # by the row's first column, and drew the board there)
    tg = Target.chessboard(40, 40, 0.1)
    cam = replace(SMALL, blur_sigma_px=0.0, noise_std=0.0)
    R_board_cam = Rx(np.radians(80.0)) @ Rz(np.radians(-30.0))  # 10 deg towards the board
    R = R_board_cam.T
    c = np.array([2.0, 2.0, -0.3])  # the camera centre, board frame (print side: z < 0)
    T = T_from_Rt(R, -R @ c)
    img = render.render_target(tg, cam, T, np.random.default_rng(0)).astype(float) / 255.0
    u, v = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    d_cam = np.stack([(u - 160.0) / 400.0, (v - 120.0) / 400.0, np.ones_like(u, float)], -1)
    away = (d_cam @ R_board_cam.T)[..., 2] <= -0.01  # board +z is away from the print side
    towards = (d_cam @ R_board_cam.T)[..., 2] >= 0.01
    assert away.sum() > 1000 and towards.sum() > 1000
    assert np.allclose(img[away], render.BACKGROUND, atol=2.0 / 255.0)
    assert img[towards].std() > 0.1  # the board, seen


def test_back_of_the_board_is_plain_and_misses_show_background():
    tg = Target.charuco(5, 4, 0.03, 0.022)
    cam = replace(SMALL, noise_std=0.0)
    T = _facing(tg, 0.3, R=Ry(np.pi))  # seen from +z: the back
    img = render.render_target(tg, cam, T, np.random.default_rng(0)).astype(float)
    levels = np.array([render.BACK, render.BACKGROUND]) * 255
    assert img.min() >= levels.min() - 1 and img.max() <= levels.max() + 1
    assert np.any(np.abs(img - render.BACK * 255) < 1)  # the board is in view
    # pointing away from the board: background only
    T_away = _facing(tg, -0.3)
    img = render.render_target(tg, cam, T_away, np.random.default_rng(0))
    assert np.all(np.abs(img.astype(float) - render.BACKGROUND * 255) <= 1)


def test_noise_exposure_and_clipping():
    tg = Target.charuco(5, 4, 0.03, 0.022)
    cam = replace(SMALL, noise_std=3.0, blur_sigma_px=0.0)
    T = _facing(tg, 2.0)  # small board in the middle; the corners of the image are background
    img = render.render_target(tg, cam, T, np.random.default_rng(3)).astype(float)
    patch = img[:60, :60]
    assert abs(patch.mean() - render.BACKGROUND * 255) < 0.5
    assert abs(patch.std() - 3.0) < 0.3  # 3600 samples: std of the std ~ 0.04
    bright = render.render_target(tg, replace(cam, exposure=4.0), T, np.random.default_rng(3))
    assert bright.dtype == np.uint8 and bright.max() == 255  # clipped, not wrapped
    assert np.all(bright[:60, :60] == 255)


def test_colour_vignetting_and_determinism():
    tg = Target.charuco(5, 4, 0.03, 0.022)
    cam = replace(SMALL, colour=True)
    T = _facing(tg, 0.3)
    a = render.render_target(tg, cam, T, np.random.default_rng(5))
    b = render.render_target(tg, cam, T, np.random.default_rng(5))
    assert a.shape == (240, 320, 3) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)
    flat = replace(SMALL, noise_std=0.0)
    away = _facing(tg, -0.3)
    v = render.render_target(tg, flat, away, np.random.default_rng(0), vignetting=0.3)
    assert v[120, 160] > v[0, 0] + 0.2 * render.BACKGROUND * 255


def test_points_target_cannot_be_rendered():
    tg = Target.points(np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) * 0.1)
    with pytest.raises(InputError):
        render.render_target(tg, SMALL, np.eye(4), np.random.default_rng(0))


def test_full_size_render_is_fast():
    tg = Target.charuco(11, 8, 0.03, 0.022)
    cam = single_camera()
    T = _facing(tg, 0.5, R=Rx(np.radians(30)))
    rng = np.random.default_rng(0)
    render.render_target(tg, cam, T, rng)  # warms the per-camera and texture caches
    # the process's CPU time, not the wall clock: a machine busy with other work (a CI runner,
    # benchmarks alongside) stretched the wall time of this 0.2 s render past 3 s
    t0 = time.process_time()
    img = render.render_target(tg, cam, T, rng)
    elapsed = time.process_time() - t0
    assert img.shape == (800, 1280)
    assert elapsed < 1.0


def _rig(poses, cameras=None):
    tg = Target.charuco(5, 4, 0.03, 0.022)
    cams = cameras or [SMALL, replace(SMALL, name="second", colour=True)]
    return SimulatedCameraRig(cams, tg, poses, np.random.default_rng(0)), tg


def test_rig_protocol_truth_and_faults():
    from slidecal.drivers.base import CameraRig

    state = {"z": 0.3}

    def poses():
        T = _facing(Target.charuco(5, 4, 0.03, 0.022), state["z"])
        return {"small": T, "second": T}

    rig, _ = _rig(poses)
    assert isinstance(rig, CameraRig)
    assert [s.name for s in rig.specs] == ["small", "second"]
    with pytest.raises(HardwareFault):
        rig.capture()
    rig.open()
    rig.inject_fault("no_frame", at_capture=1)
    rig.inject_fault("disconnect", at_capture=3)
    images = rig.capture()
    assert images["small"].shape == (240, 320) and images["second"].shape == (240, 320, 3)
    np.testing.assert_allclose(rig.last_poses["small"], poses()["small"])
    with pytest.raises(HardwareFault):
        rig.capture()  # dropped frame
    state["z"] = 0.4
    rig.capture()  # works again
    assert rig.last_poses["small"][2, 3] == pytest.approx(0.4)
    for _ in range(2):
        with pytest.raises(HardwareFault):
            rig.capture()  # disconnected until reopened
    rig.close()
    rig.close()
    rig.open()
    rig.capture()
    with pytest.raises(InputError):
        rig.inject_fault("smoke", at_capture=0)


def test_presets():
    r1 = single_camera()
    np.testing.assert_allclose(r1.K, K_matrix(880.0, 880.0, 640.0, 400.0))
    np.testing.assert_allclose(r1.dist, [-0.12, 0.05, 5e-4, -3e-4, 0.0])
    assert (r1.width, r1.height) == (1280, 800)
    cams = {c.name: c for c in oak_d_like(noise_std=1.0)}
    assert set(cams) == {"left", "right", "rgb"}
    assert (cams["left"].width, cams["left"].height) == (1280, 800)
    assert cams["rgb"].colour and not cams["left"].colour and cams["right"].noise_std == 1.0
    hfov_mono = 2 * np.degrees(np.arctan(640 / cams["left"].K[0, 0]))
    hfov_rgb = 2 * np.degrees(np.arctan(960 / cams["rgb"].K[0, 0]))
    assert 70 < hfov_mono < 74 and hfov_rgb < hfov_mono
    ext = oak_d_like_extrinsics()
    T_right_left = ext["right"]
    assert np.linalg.norm(T_right_left[:3, 3]) == pytest.approx(0.075, abs=1e-3)
    # the right camera sees the left camera's origin at negative x (it sits to the left)
    assert T_right_left[0, 3] < -0.07
    np.testing.assert_allclose(ext["left"], np.eye(4))
    assert ext["rgb"][0, 3] == pytest.approx(-0.0375, abs=1e-3)
    np.testing.assert_allclose(ext["rgb"][:3, :3] @ ext["rgb"][:3, :3].T, np.eye(3), atol=1e-12)


# ----------------------------------------------------------------------------- photograph-like

# the photo pipeline with every effect off (equals the clean renderer but for the noise draw)
FLAT = render.Photo(
    aperture_mm=0.0,
    chromatic_red=0.0,
    chromatic_blue=0.0,
    full_well_e=0.0,
    bayer=False,
    jpeg_quality=0,
    vignetting=0.0,
    gradient=0.0,
    glare_spots=0,
)


def test_photo_is_seeded_and_shaped_like_a_camera_image():
    tg = Target.chessboard(7, 6, 0.03)
    T = _facing(tg, 0.4, R=Rx(np.radians(20)))
    colour = replace(SMALL, colour=True, photo=render.Photo())
    a = render.render_target(tg, colour, T, np.random.default_rng(1))
    b = render.render_target(tg, colour, T, np.random.default_rng(1))
    assert a.shape == (240, 320, 3) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)
    mono = render.render_target(
        tg, replace(SMALL, photo=render.Photo()), T, np.random.default_rng(1)
    )
    assert mono.shape == (240, 320) and mono.dtype == np.uint8
    with pytest.raises(InputError):
        render.Photo(jpeg_quality=120)


def test_photo_shot_noise_follows_the_signal():
    # a flat grey background, no light effects: variance = read^2 + signal / (electrons per DN)
    tg = Target.chessboard(7, 6, 0.03)
    photo = replace(FLAT, full_well_e=2000.0)
    cam = replace(SMALL, noise_std=1.0, blur_sigma_px=0.0, photo=photo)
    img = render.render_target(tg, cam, _facing(tg, -0.3), np.random.default_rng(2)).astype(float)
    signal = render.BACKGROUND * 255
    expected = np.sqrt(1.0 + signal / (2000.0 / 255.0) + 1.0 / 12.0)  # + quantisation
    assert abs(img.mean() - signal) < 0.3
    assert img.std() == pytest.approx(expected, rel=0.05)  # 76800 samples


def test_photo_defocus_grows_away_from_the_focus_distance():
    s = render.defocus_sigma_px(render.Photo(aperture_mm=4.0), 1000.0, np.array([2.0, 1.0]), 2.0)
    np.testing.assert_allclose(s, [0.0, 0.25 * 1000 * 0.004 * 1.0])
    # a board tilted 60 deg, focused on its near side: its far side is blurred
    tg = Target.chessboard(9, 6, 0.03)
    T = _facing(tg, 0.35, R=Ry(np.radians(60)))
    photo = replace(FLAT, aperture_mm=20.0, focus_distance_m=0.27)  # far side: sigma ~3 px
    cam = replace(SMALL, noise_std=0.0, photo=photo)
    img = render.render_target(tg, cam, T, np.random.default_rng(3))
    truth = project(cam.K, cam.dist, tg.points_m @ T[:3, :3].T + T[:3, 3])
    z = (tg.points_m @ T[:3, :3].T + T[:3, 3])[:, 2]
    near, far = truth[np.argmin(z)], truth[np.argmax(z)]

    def steepest(p):
        u, v = np.rint(p).astype(int)
        patch = img[v - 6 : v + 7, u - 6 : u + 7].astype(float)
        return np.abs(np.diff(patch, axis=1)).max()

    assert steepest(near) > 2.0 * steepest(far)


def test_photo_chromatic_aberration_moves_red_and_blue_against_green():
    # vertical edges on the principal point's row, located by area (as in the first test):
    # red lies 1 + 2e-3 times as far from the principal point as green, blue 1 - 2e-3
    tg = Target.chessboard(9, 7, 0.02)
    photo = replace(FLAT, chromatic_red=2e-3, chromatic_blue=-2e-3)
    cam = replace(SMALL, noise_std=0.0, colour=True, photo=photo)
    T = _facing(tg, 0.3)  # the principal point's row runs through the middle of a square row
    img = render.render_target(tg, cam, T, np.random.default_rng(4)).astype(float)
    lo, hi = render.BLACK * 255, render.WHITE * 255
    cx, cy = cam.K[0, 2], int(cam.K[1, 2])
    square_px = 0.02 * 400 / 0.3
    shifts = {0: [], 2: []}
    for k in (-4, -3, 3, 4):
        edge = cx + (k - 0.5 * np.sign(k)) * square_px
        a = int(np.floor(edge)) - 8
        pos = []
        for ch in (0, 1, 2):
            row = img[cy, a : a + 17, ch]
            frac = (row - lo) / (hi - lo)
            if frac[0] < 0.5:  # the fraction of the left-hand colour
                frac = 1.0 - frac
            pos.append(a - 0.5 + frac.sum())
        for ch in (0, 2):
            shifts[ch].append((pos[ch] - pos[1], pos[1] - cx))
    for ch, scale in ((2, 2e-3), (0, -2e-3)):
        for d, r in shifts[ch]:
            assert d == pytest.approx(scale * r, abs=0.02)  # 0.1-0.2 px


def test_photo_light_is_uneven_and_glare_brightens():
    tg = Target.chessboard(7, 6, 0.03)
    away = _facing(tg, -0.3)
    cam = replace(SMALL, noise_std=0.0)
    lit = replace(FLAT, vignetting=0.3, gradient=0.4)
    img = render.render_target(tg, replace(cam, photo=lit), away, np.random.default_rng(5))
    assert img[120, 160] > img[0, 0] and img.max() - img.min() > 0.2 * render.BACKGROUND * 255
    glare = replace(FLAT, glare_spots=1, glare_strength=0.5)
    g = render.render_target(tg, replace(cam, photo=glare), away, np.random.default_rng(5))
    assert g.max() > render.BACKGROUND * 255 + 0.4 * 255


def test_photo_jpeg_and_bayer_stay_close_to_the_clean_image():
    tg = Target.chessboard(7, 6, 0.03)
    T = _facing(tg, 0.4)
    cam = replace(SMALL, noise_std=0.0, colour=True)
    clean = render.render_target(tg, replace(cam, photo=FLAT), T, np.random.default_rng(6))
    jb = replace(FLAT, bayer=True, jpeg_quality=90)
    img = render.render_target(tg, replace(cam, photo=jb), T, np.random.default_rng(6))
    d = img.astype(float) - clean.astype(float)
    assert 0.3 < np.abs(d).mean() < 6.0  # changed, but only near edges and by a few levels


def test_tag_prints_are_exact_off_the_texel_grid():
    # corners of an AprilGrid and of a lone tag, noise-free: cornerSubPix started at the truth
    # stays there (a print whose edges snapped to texels was off by up to 0.2 px)
    cam = replace(single_camera(), noise_std=0.0, dist=np.zeros(5))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    tg = Target.aprilgrid(6, 5, 0.03, 0.3)
    w, h = render.extent_m(tg)
    T = T_from_Rt(np.eye(3), np.array([-w / 2, -h / 2, 0.6]))
    img = render.render_target(tg, cam, T, np.random.default_rng(7))
    truth = project(cam.K, cam.dist, tg.points_m + T[:3, 3]).astype(np.float32)
    c = cv2.cornerSubPix(img, truth.reshape(-1, 1, 2).copy(), (5, 5), (-1, -1), crit)
    e = c.reshape(-1, 2) - truth
    # cornerSubPix locks to pixels by a few hundredths (test_corners_agree_with_the_lens_model);
    # a print with edges snapped to texels gave 0.17 px rms
    assert np.abs(e).max() < 0.12 and np.sqrt(np.mean(np.sum(e * e, axis=1))) < 0.08

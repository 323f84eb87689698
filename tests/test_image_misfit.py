"""An image's errors taken together: the frames' scores, the neighbouring corners' residual
correlation that decides whether they are read, and what that does on real photographs
(solver/robot_error.py ``cluster_excess``, docs/METHOD.md Sec. 6)."""

from __future__ import annotations

import glob
import shutil
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

import slidecal.solver.robot_error as named_mod
from slidecal.mocks import scenarios as sc
from slidecal.mocks.scenarios import one_tag_geometry, one_tag_session, render_detector
from slidecal.solver.calibrate import calibrate
from slidecal.solver.robot_error import (
    CORRELATED_NEIGHBOURS,
    _neighbour_pairs,
    images_err_together,
    neighbour_correlation,
)
from tests.session_io import read_session

sys.path.insert(0, str(Path(__file__).parent))
from test_named import _solve_keeping_the_refinement  # noqa: E402

DATA = Path(__file__).parent / "data"
P = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}


def _model_only(monkeypatch) -> None:  # noqa: ANN001
    """No reading of the detections' errors taken together: the model's covariance alone."""
    monkeypatch.setattr(named_mod, "CORRELATED_NEIGHBOURS", 10.0)
    monkeypatch.setattr(named_mod, "MISFIT_IMAGE_P", 0.0)
    monkeypatch.setattr(named_mod, "GROUPED_ERRORS_P", 0.0)


def _photographs(root: Path, camera: str):  # noqa: ANN202
    """OpenCV's 13 sample photographs of one camera as an images-only session."""
    s = root / camera
    (s / "images").mkdir(parents=True)
    files = sorted(glob.glob(str(DATA / f"opencv_{camera}" / "*.jpg")))
    for f in files:
        shutil.copy(f, s / "images")
    session = {
        "format": "slidecal.session/1",
        "target": {"kind": "chessboard", "squares_x": 10, "squares_y": 7, "square_size_m": 0.025},
        "cameras": [{"name": "cam", "width": 640, "height": 480}],
        "frames": [
            {"id": k, "images": {"cam": f"images/{Path(f).name}"}} for k, f in enumerate(files)
        ],
    }
    (s / "session.yaml").write_text(yaml.safe_dump(session))
    return read_session(s)


@pytest.mark.parametrize("exact", [False, True])
def test_frame_scores_are_the_gradient_frame_by_frame(monkeypatch, exact):
    # with the arm's accuracy learned (pose corrections, their groups and trends as shared
    # columns) and with exact poses: each frame's score is the normal equations' right-hand
    # side of its rows alone, and they sum to the pixel rows' one
    s = sc.r1(np.random.default_rng(3), 0.15, *((0.0, 0.0) if exact else (5e-5, 0.005)))
    _, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    m = out.model
    assert ("E" in m.slices) is not exact
    w = np.asarray(m.row_weights, float)
    scores = m.frame_scores(out.state, w)
    pixels = w.copy()
    pixels[len(out.residuals) :] = 0.0
    whole = m.normal_blocks(out.state, pixels, keep=False).g_g
    assert scores.shape == (len(m.frame_rows), len(whole))
    assert np.allclose(scores.sum(axis=0), whole, rtol=0, atol=1e-9 * np.abs(scores).max())
    for k, (_, rows) in enumerate(list(m.frame_rows.items())[:3]):
        mask = np.zeros(len(w))
        mask[rows] = 1.0
        one = m.normal_blocks(out.state, w * mask, keep=False).g_g
        assert np.allclose(scores[k], one, rtol=0, atol=1e-9 * np.abs(one).max())


def test_independent_detections_leave_the_covariance_as_it_was(monkeypatch):
    # simulated detections with independent noise: neighbouring residuals do not go together
    # (the fit itself makes them slightly negative), so nothing is added
    for s in (sc.r1_real_arm(np.random.default_rng(2001)), sc.s2(5, 0.5, np.random.default_rng(1))):
        res, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
        rho, pairs = neighbour_correlation(out)
        assert pairs > 500 and -0.1 < rho < 0.05
        monkeypatch.setattr(named_mod, "CORRELATED_NEIGHBOURS", -10.0)  # read them anyway
        forced = calibrate(s.problem)
        monkeypatch.setattr(named_mod, "CORRELATED_NEIGHBOURS", CORRELATED_NEIGHBOURS)
        for p in P:
            assert forced.cameras["cam"].std[p] >= res.cameras["cam"].std[p]  # only widens
        assert res.cameras["cam"].std == calibrate(s.problem).cameras["cam"].std


def _lines_shifted(problem, shift_px: float, rng: np.random.Generator):  # noqa: ANN001, ANN202
    """Every line of the board's corners shifted across itself in every image by its own
    Gaussian amount (one std ``shift_px``), on top of the detections' own noise: an edge's
    error moving the corners on it together (the print, blur, the light)."""
    pts = problem.target.points_m
    row = np.unique(np.round(pts[:, 1], 9), return_inverse=True)[1]
    col = np.unique(np.round(pts[:, 0], 9), return_inverse=True)[1]
    frames = []
    for f in problem.frames:
        d = f.detections["cam"]
        q = pts[d.ids, :2]
        # the board's axes in this image (to first order about its centre)
        A = np.linalg.lstsq(np.c_[q - q.mean(axis=0), np.ones(len(q))], d.px, rcond=None)[0]
        across = []
        for axis in A[:2]:
            u = axis / np.linalg.norm(axis)
            across.append(np.array([-u[1], u[0]]))
        px = d.px.copy()
        px += rng.normal(0.0, shift_px, row.max() + 1)[row[d.ids], None] * across[0]
        px += rng.normal(0.0, shift_px, col.max() + 1)[col[d.ids], None] * across[1]
        frames.append(replace(f, detections={"cam": replace(d, px=px)}))
    return replace(problem, frames=tuple(frames))


def _pooled(out) -> float:  # noqa: ANN001
    """The neighbouring corners' residual vectors' mean product over their mean square: both
    directions at once (how the previous release read them)."""
    m = out.model
    a, b = _neighbour_pairs(m.problem.target.points_m)
    e = out.residuals[: 2 * m.n_obs].reshape(-1, 2)
    num, pairs = 0.0, 0
    for ch in m.chunks:
        row = np.full(len(m.problem.target.points_m), -1)
        row[ch.corner_ids] = ch.rows.start // 2 + np.arange(len(ch.corner_ids))
        both = (row[a] >= 0) & (row[b] >= 0)
        num += float(np.sum(e[row[a][both]] * e[row[b][both]]))
        pairs += int(both.sum())
    return num / pairs / float(np.mean(np.sum(e**2, axis=1)))


def test_an_edge_error_shared_along_the_board_lines_is_read(monkeypatch):
    # what rendered images show (0.08-0.17 across the lines, nothing along them): read pooled
    # over both directions it stayed under a gate it passes when read across
    s = sc.r1_real_arm(np.random.default_rng(2001))
    problem = _lines_shifted(s.problem, 0.07, np.random.default_rng(5))
    res, out = _solve_keeping_the_refinement(problem, monkeypatch)
    rho, pairs = neighbour_correlation(out)
    assert rho > CORRELATED_NEIGHBOURS + 2.0 / np.sqrt(pairs)
    assert images_err_together(out)[0] == (rho, pairs)
    assert any("neighbouring corners go together" in m for m in res.messages)
    # the two directions pooled (their mean) read half: under the previous gate of 0.1
    assert _pooled(out) < 0.1 + 2.0 / np.sqrt(pairs)
    _model_only(monkeypatch)
    model_only = calibrate(problem).cameras["cam"].std
    for p in P:
        assert res.cameras["cam"].std[p] >= model_only[p]
    # measured: fx, fy, cx, cy 1.15, 1.13, 1.05, 1.22 times the model's
    assert max(res.cameras["cam"].std[p] / model_only[p] for p in P) > 1.1


@pytest.mark.slow
def test_rendered_photographs_read_their_errors_across_the_board_lines(monkeypatch):
    # mocks/render.py's photograph-like images of R1 on a real arm, detected: their corners
    # err together across the board's lines (0.08-0.17 over 120 arms) and not along them, so
    # the frames' scores are read; pooled they stayed under the previous gate

    s = sc.r1_real_arm(np.random.default_rng(2000), detect=render_detector())
    res, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    rho, pairs = neighbour_correlation(out)
    assert rho > CORRELATED_NEIGHBOURS + 2.0 / np.sqrt(pairs)
    assert _pooled(out) < 0.1 + 2.0 / np.sqrt(pairs)
    assert any("neighbouring corners go together" in m for m in res.messages)


def test_a_lone_tag_says_nothing_of_its_corners_correlation(monkeypatch):
    # 4 corners an image: the pose takes 6 of their 8 residuals' freedom, and their
    # correlation is the fit's (independent noise read 0.28-0.36 on 9 of 100 draws of this
    # session before such images were left out); nothing is read, nothing added
    s = one_tag_session(np.random.default_rng(1087), one_tag_geometry())  # one of the nine
    _, out = _solve_keeping_the_refinement(s.problem, monkeypatch)
    assert neighbour_correlation(out) == (0.0, 0)
    assert images_err_together(out)[0] is None


def test_real_photographs_carry_their_correlated_errors(tmp_path, monkeypatch):
    # OpenCV's sample photographs: neighbouring corners' residuals correlate by 0.47 (the larger
    # of along and across their line), far beyond the gate; the principal point's std then
    # comes from the frames' scores, two to three times the model's (measured: cx 0.42 -> 1.46
    # px, cy 0.49 -> 1.01 px on left)
    problem = _photographs(tmp_path, "left")
    res, out = _solve_keeping_the_refinement(problem, monkeypatch)
    rho, pairs = neighbour_correlation(out)
    assert rho > CORRELATED_NEIGHBOURS + 2.0 / np.sqrt(pairs) and rho > 0.25
    _model_only(monkeypatch)
    model_only = calibrate(problem).cameras["cam"].std
    ours = res.cameras["cam"].std
    assert ours["cx"] > 2.0 * model_only["cx"] and ours["cy"] > 1.5 * model_only["cy"]
    assert all(ours[p] >= model_only[p] for p in P)


@pytest.mark.slow
@pytest.mark.parametrize("camera", ["left", "right"])
def test_real_photographs_halves_agree_within_the_reported_std(tmp_path, monkeypatch, camera):
    # no truth for real photographs, but two disjoint halves of one camera's session must
    # agree within their reported std: split 30 ways (6 against 7 images), the differences
    # over sqrt(std_a^2 + std_b^2) have an rms near 1 when the std are honest. Measured: with
    # each corner's error taken as its own, cx 3.3-3.8 and cy 2.0-2.2 (fx 1.1-2.1); read
    # image by image, 1.1-1.4 on all four
    problem = _photographs(tmp_path, camera)
    rng = np.random.default_rng(0)

    def z_rms() -> dict[str, float]:
        z = {p: [] for p in P}
        for _ in range(30):
            perm = rng.permutation(len(problem.frames))
            a, b = (
                calibrate(replace(problem, frames=tuple(problem.frames[i] for i in sorted(h))))
                for h in (perm[:6], perm[6:])
            )
            ca, cb = a.cameras["cam"], b.cameras["cam"]
            for p, (i, j) in P.items():
                z[p].append((ca.K[i, j] - cb.K[i, j]) / np.hypot(ca.std[p], cb.std[p]))
        return {p: float(np.sqrt(np.mean(np.square(v)))) for p, v in z.items()}

    ours = z_rms()
    assert max(ours.values()) < 1.6, ours
    _model_only(monkeypatch)
    model_only = z_rms()
    assert model_only["cx"] > 2.5 and model_only["cy"] > 1.6, model_only


def _glare(problem, frame: int, shift_px: float):  # noqa: ANN001, ANN202
    """The corners of one image within two board squares of its centremost corner moved
    together by ``shift_px`` along x (a specular highlight on the board biases the corners
    under it alike; the image's other corners keep their own noise)."""
    f = problem.frames[frame]
    d = f.detections["cam"]
    centre = d.px[np.argmin(np.linalg.norm(d.px - d.px.mean(axis=0), axis=1))]
    pitch = np.median(np.linalg.norm(np.diff(d.px, axis=0), axis=1))
    near = np.linalg.norm(d.px - centre, axis=1) < 2.0 * pitch
    px = d.px.copy()
    px[near, 0] += shift_px
    frames = list(problem.frames)
    frames[frame] = replace(f, detections={"cam": replace(d, px=px)})
    return replace(problem, frames=tuple(frames)), int(near.sum())


def test_a_small_misfit_of_one_image_among_many_is_not_read(monkeypatch):
    # the same glare at 0.6 px: significant (its image 1.3 times the noise) but under a tenth of
    # the session's squares, so the model's covariance stands (as on real photographs whose
    # images differ a little in sharpness)
    s = sc.r1_real_arm(np.random.default_rng(2001))
    problem, _ = _glare(s.problem, 5, 0.6)
    res, out = _solve_keeping_the_refinement(problem, monkeypatch)
    assert images_err_together(out)[1] is None
    monkeypatch.setattr(named_mod, "MISFIT_IMAGE_SHARE", 0.0)
    assert images_err_together(out)[1][0] == 5


def test_independent_detections_leave_every_image_within_its_noise(monkeypatch):
    for seed in (2000, 2001, 2002):
        _, out = _solve_keeping_the_refinement(
            sc.r1_real_arm(np.random.default_rng(seed)).problem, monkeypatch
        )
        assert images_err_together(out)[1] is None


def test_a_few_corners_of_one_image_erring_together_are_read(monkeypatch):
    # what the neighbours' correlation does not see: a glare spot moving a dozen corners of one
    # image alike by 1 px (7 times the corner noise). That image's residuals are beyond what
    # independent errors give, by a tenth of the session's squares or more, so the frames'
    # scores are read and the std widen
    s = sc.r1_real_arm(np.random.default_rng(2001))
    problem, moved = _glare(s.problem, 5, 1.0)
    assert moved >= 8
    res, out = _solve_keeping_the_refinement(problem, monkeypatch)
    rho, pairs = neighbour_correlation(out)
    assert rho < CORRELATED_NEIGHBOURS + 2.0 / np.sqrt(pairs)  # the neighbours do not tell
    frame, ratio, p = images_err_together(out)[1]
    assert frame == 5 and ratio > 1.3 and p < named_mod.MISFIT_IMAGE_P
    note = [m for m in res.messages if "image by image" in m]
    assert len(note) == 1 and f"frame {problem.frames[5].id} are" in note[0]
    _model_only(monkeypatch)
    model_only = calibrate(problem).cameras["cam"].std
    assert all(res.cameras["cam"].std[p] >= model_only[p] for p in P)
    assert max(res.cameras["cam"].std[p] / model_only[p] for p in P) > 1.05


def test_too_few_frames_to_read_image_by_image_say_nothing_of_it(monkeypatch):
    # three images of one glare: the frames' scores need four frames at least, so the
    # covariance stays the model's and no line says it was read image by image
    s = sc.s2(3, 0.2, np.random.default_rng(4))
    problem, _ = _glare(s.problem, 1, 2.0)
    res = calibrate(problem)
    assert not any("image by image" in m for m in res.messages)


def _tag_corner_biased(problem, group_frames, corner, shift_px):
    """``problem`` with one corner of the tag moved by ``shift_px`` on every frame of
    ``group_frames``: a detector's fixed pattern at one view."""
    frames = list(problem.frames)
    for k in group_frames:
        det = frames[k].detections["cam"]
        px = det.px.copy()
        px[det.ids == corner] += shift_px
        frames[k] = replace(frames[k], detections={"cam": replace(det, px=px)})
    return replace(problem, frames=tuple(frames))


def test_a_fixed_pattern_at_one_orientation_is_read_group_by_group(monkeypatch):
    # the eye-to-hand tag session (205 frames of a lone tag's 4 corners, 7 orientations): no
    # image shows a corner that errs alike on every frame at one orientation; the corners'
    # mean residuals per group do. Independent detections: not read, no line
    from slidecal.solver.model import orientation_groups

    s = sc.tag_real_arm(np.random.default_rng(2002), sigma_px=0.15, arm_mm=1.0, arm_deg=0.1)
    clean = calibrate(s.problem)
    assert not [m for m in clean.messages if "orientation group" in m]
    groups = orientation_groups(np.stack([f.T_base_tool for f in s.problem.frames]))
    biased = _tag_corner_biased(
        s.problem, np.flatnonzero(groups == groups[100]), 3, np.array([0.25, 0.25])
    )
    res = calibrate(biased)
    (note,) = [m for m in res.messages if "orientation group" in m]
    assert "group by group" in note
    _model_only(monkeypatch)
    model = calibrate(biased)
    assert not [m for m in model.messages if "orientation group" in m]
    for name in P:  # the groups' spread widens the std (never narrows it)
        assert res.cameras["cam"].std[name] >= model.cameras["cam"].std[name] * (1 - 1e-9)
    for name, (a, b) in P.items():
        err = res.cameras["cam"].K[a, b] - s.truth.K["cam"][a, b]
        assert abs(err) < 3.0 * res.cameras["cam"].std[name], name

"""Session and cell writers/readers only the tests and benchmarks need (the product writes a
session frame by frame with ``SessionWriter`` and reads it with ``load_session``), and the
edits that make a good session or problem into a user's mistake."""

from __future__ import annotations

import shutil
from collections.abc import Mapping
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from slidecal.mocks.camera import SimCamera
from slidecal.routines.config import CELL_KEYS, POSE_NAMES, CellConfig, config_to_dict
from slidecal.routines.schema import plain, write_yaml
from slidecal.routines.session import (
    SESSION_FILE,
    SessionWriter,
    load_session,
    transform_to_dict,
)
from slidecal.solver.problem import CalibrationProblem, CameraSpec, Detection


def read_session(directory: str | Path, detect_images: bool = True) -> CalibrationProblem:
    """The :class:`CalibrationProblem` a session directory holds (:func:`load_session`)."""
    return load_session(directory, detect_images=detect_images).problem



def write_session(
    directory: str | Path,
    problem: CalibrationProblem,
    simulation: Mapping[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a problem (detections only, no images) as a session directory (``overwrite``: over
    the session it holds)."""
    if overwrite:
        (Path(directory) / SESSION_FILE).unlink(missing_ok=True)
    w = SessionWriter(
        directory,
        problem.target,
        problem.cameras,
        mount=problem.mount,
        knowledge=problem.knowledge,
        options=problem.options,
        reference_camera=problem.reference_camera,
        simulation=simulation,
    )
    for fr in problem.frames:
        w.append_frame(
            fr.T_base_tool,
            detections=fr.detections,
            group=fr.group,
            motion_board=fr.motion_board,
            frame_id=fr.id,
        )
    return w.finish()


def write_config(cfg: CellConfig, path: str | Path) -> Path:
    """Write the cell file of ``cfg``: :func:`config_to_dict`, its ``cameras:`` after ``robot``,
    and a simulated cell's truth in full (no preset) after ``approximate``."""
    out = config_to_dict(cfg)
    cameras: dict[str, Any] = {"driver": cfg.camera_driver, "reference": cfg.reference_camera}
    if cfg.device_id is not None:
        cameras["device_id"] = cfg.device_id
    cameras.update(cfg.rig_options)
    if cfg.camera_driver != "simulated":
        cameras["list"] = [
            {"name": c.name, "width": c.width, "height": c.height, **cfg.camera_options[c.name]}
            for c in cfg.cameras
        ]
    keys = list(out)
    out = {**{k: out[k] for k in keys[:3]}, "cameras": cameras, **{k: out[k] for k in keys[3:]}}
    sim = cfg.simulation
    if sim is not None:
        he_key, tg_key = POSE_NAMES[cfg.mount]
        truth: dict[str, Any] = {
            "seed": sim.seed,
            "cameras": {c.name: _sim_camera_to_dict(c) for c in sim.cameras},
            he_key: transform_to_dict(sim.T_hand_eye),
            tg_key: transform_to_dict(sim.T_target),
            "rig": {n: transform_to_dict(T) for n, T in sim.rig.items()},
            "noise": {"robot_mm": sim.robot_noise_m * 1000.0, "robot_deg": sim.robot_noise_deg},
            "target_jitter": {"mm": sim.target_jitter_mm, "deg": sim.target_jitter_deg},
        }
        if sim.kinematic_error is not None:
            truth["kinematic_error"] = dict(sim.kinematic_error)
        if any(sim.board_bow_mm):
            truth["board_bow_mm"] = list(sim.board_bow_mm)
        keys = list(out)
        at = keys.index("approximate") + 1
        out = {**{k: out[k] for k in keys[:at]}, "simulation": truth,
               **{k: out[k] for k in keys[at:]}}  # fmt: skip
    return write_yaml(path, out)


def _sim_camera_to_dict(c: SimCamera) -> dict[str, Any]:
    """A ``simulation.cameras.<name>`` entry in full (``distortion`` is the camera's ``dist``)."""
    keys = CELL_KEYS["simulation.cameras.*"]
    out = {k: plain(getattr(c, "dist" if k == "distortion" else k)) for k in keys}
    out["photo"] = asdict(c.photo) if c.photo is not None else False
    return out


# ------------------------------------------- a user's mistakes: problems and session files edited
def scale_pixels(problem: CalibrationProblem, factor: Mapping[str, float]) -> CalibrationProblem:
    """The problem with camera ``c``'s pixels and image size multiplied by ``factor[c]``: ``K``
    becomes ``diag(f, f, 1) K``, distortion unchanged, so equal row weights on it are per-camera
    weights ``1 / sigma_c^2`` when ``factor[c] = sigma_ref / sigma_c``."""
    frames = []
    for fr in problem.frames:
        dets = {c: Detection(d.ids, d.px * factor.get(c, 1.0)) for c, d in fr.detections.items()}
        frames.append(replace(fr, detections=dets))
    cams = tuple(
        CameraSpec(
            c.name,
            round(c.width * factor.get(c.name, 1.0)),
            round(c.height * factor.get(c.name, 1.0)),
        )
        for c in problem.cameras
    )
    return replace(problem, frames=tuple(frames), cameras=cams)


def centre_only(problem: CalibrationProblem, frac: float) -> CalibrationProblem:
    """The problem with only the corners within the central ``frac`` of each image's width and
    height (a session whose views never reached the image's edges)."""
    frames = []
    for f in problem.frames:
        dets = {}
        for c, d in f.detections.items():
            spec, px = problem.camera(c), np.asarray(d.px)
            keep = np.all(np.abs(px / [spec.width, spec.height] - 0.5) < frac / 2, axis=1)
            dets[c] = Detection(d.ids[keep], px[keep])
        frames.append(replace(f, detections=dets))
    return replace(problem, frames=tuple(frames))


def swap_cameras(problem: CalibrationProblem, a: str, b: str) -> CalibrationProblem:
    """The problem with cameras ``a`` and ``b``'s detections exchanged in every frame (a stereo
    head's left and right images swapped; the two must have one image size)."""
    frames = []
    for fr in problem.frames:
        dets = dict(fr.detections)
        dets[a], dets[b] = fr.detections.get(b), fr.detections.get(a)
        frames.append(replace(fr, detections={c: d for c, d in dets.items() if d is not None}))
    return replace(problem, frames=tuple(frames))


def focus_changed(
    problem: CalibrationProblem, camera: str, K: np.ndarray, factor: float, start: int
) -> CalibrationProblem:
    """The problem with ``camera``'s focal lengths ``factor`` times longer from frame index
    ``start`` on (a focus ring turned mid-session): its pixels scaled about the principal point
    of ``K``, the true intrinsics (the distortion acts before ``K``, so this is exact)."""
    c = np.asarray(K, dtype=float)[:2, 2]
    frames = list(problem.frames)
    for k in range(start, len(frames)):
        dets = dict(frames[k].detections)
        if camera in dets:
            d = dets[camera]
            dets[camera] = Detection(d.ids, c + factor * (np.asarray(d.px, float) - c))
        frames[k] = replace(frames[k], detections=dets)
    return replace(problem, frames=tuple(frames))


def copy_session(src: Path, dst: Path) -> Path:
    """The session file, its detections and plan of ``src`` (no images) in ``dst``."""
    dst.mkdir(parents=True)
    for name in ("session.yaml", "detections.npy", "plan.yaml"):
        if (src / name).is_file():
            shutil.copy(src / name, dst / name)
    return edit_session(dst, lambda doc: [f.pop("images", None) for f in doc["frames"]])


def edit_session(d: Path, fn) -> Path:  # noqa: ANN001 - fn edits the parsed document
    """Apply ``fn`` to the parsed ``session.yaml`` of ``d`` and write it back."""
    doc = yaml.safe_load((d / "session.yaml").read_text())
    fn(doc)
    (d / "session.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return d


def rotations_in_degrees(doc: dict) -> None:
    """The robot's rotation vectors written in degrees where radians are meant."""
    for f in doc["frames"]:
        p = f["T_base_tool"]
        f["T_base_tool"] = p[:3] + [float(np.degrees(v)) for v in p[3:]]


def square_size(size_m: float):  # noqa: ANN201
    """A wrong square size (the marker scaled alike) in the session's target."""

    def edit(doc: dict) -> None:
        t = doc["target"]
        t["marker_size_m"] = t["marker_size_m"] * size_m / t["square_size_m"]
        t["square_size_m"] = size_m

    return edit

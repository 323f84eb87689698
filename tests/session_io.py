"""Session and cell writers/readers only the tests and benchmarks need (the product writes a
session frame by frame with ``SessionWriter`` and reads it with ``load_session``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

from slidecal.mocks.camera import SimCamera
from slidecal.routines.config import CELL_KEYS, POSE_NAMES, CellConfig, config_to_dict
from slidecal.routines.schema import plain, write_yaml
from slidecal.routines.session import (
    SESSION_FILE,
    SessionWriter,
    load_session,
    transform_to_dict,
)
from slidecal.solver.problem import CalibrationProblem


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

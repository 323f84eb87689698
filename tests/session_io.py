"""Session and cell writers/readers only the tests and benchmarks need (the product writes a
session frame by frame with ``SessionWriter`` and reads it with ``load_session``)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from slidecal.routines.config import CellConfig, config_to_dict
from slidecal.routines.schema import write_yaml
from slidecal.routines.session import SessionWriter, load_session
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
    """Write a problem (detections only, no images) as a session directory."""
    w = SessionWriter(
        directory,
        problem.target,
        problem.cameras,
        mount=problem.mount,
        knowledge=problem.knowledge,
        options=problem.options,
        reference_camera=problem.reference_camera,
        simulation=simulation,
        overwrite=overwrite,
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
    """Write the cell file of ``cfg`` (:func:`config_to_dict`) atomically."""
    return write_yaml(path, config_to_dict(cfg))

"""A simulated robot cell: a :class:`SimulatedUR`, a :class:`SimulatedCameraRig` and the truth.

Each camera sees the board at its true ``T_cam_board``, composed from the robot's true pose
(not the measured one), the true hand-eye, rig extrinsics and target pose. The cell is a
validated ``CellConfig`` read by attribute: this package imports only ``solver`` and ``drivers``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from slidecal.drivers.ur_pose import ur_pose_from_T
from slidecal.mocks.camera import SimulatedCameraRig
from slidecal.mocks.robot import SimulatedUR
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T
from slidecal.solver.problem import MOUNTS


def _transform_dict(T: np.ndarray) -> dict[str, Any]:
    T = np.asarray(T, dtype=float)
    return {"R": T[:3, :3].tolist(), "t_m": T[:3, 3].tolist()}


def truth_block(cfg: Any, T_target: np.ndarray | None = None) -> dict[str, Any]:
    """The session's ``simulation:`` block (result-file names) of a simulated cell ``cfg``;
    ``T_target`` (4, 4): this run's target pose (default: the cell's, before jitter)."""
    sim = cfg.simulation
    frames = MOUNTS[cfg.mount]  # the result file's names
    ref = cfg.reference_camera
    out: dict[str, Any] = {
        "cameras": {
            c.name: {"K": np.asarray(c.K).tolist(), "distortion": np.asarray(c.dist).tolist()}
            for c in sim.cameras
        },
    }
    if len(sim.cameras) == 1:
        out[frames.hand_eye] = _transform_dict(sim.T_hand_eye)
    else:
        for c in sim.cameras:
            T_ref_c = np.eye(4) if c.name == ref else np.linalg.inv(sim.rig[c.name])
            out[frames.hand_eye_of(c.name)] = _transform_dict(sim.T_hand_eye @ T_ref_c)
        for name, T in sim.rig.items():
            out[f"T_{name}_{ref}"] = _transform_dict(T)
    out[frames.target] = _transform_dict(sim.T_target if T_target is None else T_target)
    out["noise"] = {
        "robot_mm": sim.robot_noise_m * 1000.0,
        "robot_deg": sim.robot_noise_deg,
        "cameras": {
            c.name: {
                "blur_sigma_px": c.blur_sigma_px,
                "noise_std": c.noise_std,
                "exposure": c.exposure,
            }
            for c in sim.cameras
        },
    }
    if sim.kinematic_error is not None:
        out["noise"]["kinematic_error"] = dict(sim.kinematic_error)
    if any(sim.board_bow_mm):
        out["board_bow_mm"] = list(sim.board_bow_mm)
    out["seed"] = sim.seed
    return out


def simulated_arm_dict(cfg: Any, seed: Any = 0) -> dict[str, Any]:
    """The ``SimulatedUR.from_dict`` description of the cell's arm (model, TCP, start pose,
    joints, limits), without measurement noise; ``seed`` for its random stream."""
    r: dict[str, Any] = {"model": cfg.robot.model, "seed": seed}
    if cfg.robot.tcp is not None:
        r["tcp"] = ur_pose_from_T(cfg.robot.tcp)
    if cfg.robot.start_pose is not None:
        r["start_pose"] = ur_pose_from_T(cfg.robot.start_pose)
    if cfg.robot.start_q is not None:
        r["start_q"] = np.asarray(cfg.robot.start_q, dtype=float).tolist()
    if cfg.robot.limits:
        r["limits"] = dict(cfg.robot.limits)
    return r


@dataclass
class SimulatedCell:
    """A simulated robot, a simulated camera rig, the ``truth`` (:func:`truth_block`) and the
    ``config`` they were built from."""

    config: Any
    robot: SimulatedUR
    rig: SimulatedCameraRig
    truth: dict[str, Any]
    seed: int

    @classmethod
    def from_config(cls, cfg: Any, seed: int | None = None) -> SimulatedCell:
        """Build the cell of a simulated ``cfg`` (``seed`` overrides ``simulation.seed``); robot and
        camera noise from independent streams."""
        sim = cfg.simulation
        if sim is None or cfg.robot.driver != "simulated":
            raise InputError(
                f"{cfg.source} describes real hardware; a SimulatedCell needs robot.driver: "
                "simulated"
            )
        seed = sim.seed if seed is None else int(seed)
        robot_seed, camera_seed, target_seed = np.random.SeedSequence(seed).spawn(3)
        rdict = simulated_arm_dict(cfg, robot_seed)
        rdict["noise"] = {"pose_noise_m": sim.robot_noise_m, "pose_noise_deg": sim.robot_noise_deg}
        if sim.kinematic_error is not None:  # a real arm's accuracy (mocks/robot.py)
            rdict["kinematic_error"] = dict(sim.kinematic_error)
        robot = SimulatedUR.from_dict(rdict)
        cams = list(sim.cameras)
        ref = cfg.reference_camera
        T_cam_ref = {c.name: (np.eye(4) if c.name == ref else sim.rig[c.name]) for c in cams}
        T_he, T_tg = sim.T_hand_eye, sim.T_target
        if sim.target_jitter_mm > 0 or sim.target_jitter_deg > 0:  # the target set up anew
            jr = np.random.default_rng(target_seed)
            dR = R_from_rvec(jr.normal(0.0, np.radians(sim.target_jitter_deg), 3))
            dt = jr.normal(0.0, sim.target_jitter_mm / 1000.0, 3)
            T_tg = T_tg @ T_from_Rt(dR, dt)
        T_ref_x = inv_T(T_he)  # T_ref_tool eye-in-hand, T_ref_base eye-to-hand
        eye_in_hand = cfg.mount == "eye_in_hand"

        def poses() -> dict[str, np.ndarray]:
            T_bt = robot.true_pose()
            T_ref_board = T_ref_x @ (inv_T(T_bt) if eye_in_hand else T_bt) @ T_tg
            return {n: T @ T_ref_board for n, T in T_cam_ref.items()}

        bow_m = (sim.board_bow_mm[0] / 1000.0, sim.board_bow_mm[1] / 1000.0)
        rig = SimulatedCameraRig(
            cams, cfg.target, poses, np.random.default_rng(camera_seed), bow_m=bow_m
        )
        truth = truth_block(cfg, T_tg)
        truth["seed"] = seed
        return cls(cfg, robot, rig, truth, seed)

"""Rehearse a cell's calibration through the real ur-rtde client (``slidecal rehearse``): the
loopback UR controller (:mod:`slidecal.mocks.ur_controller`) in its own process, the real UR
driver connected to it, the cell's routine run with simulated cameras rendering from the
controller's true pose (a real cell through its :func:`simulated_twin`), and ``rehearsal.yaml``
saying what the controller was and saw. Nothing leaves the machine; no robot moves.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.drivers.ur import URRobot
from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.mocks.cell import SimulatedCell
from slidecal.routines.acquire import new_session_dir
from slidecal.routines.config import (
    REAL_CORNER_NOISE_PX,
    CellConfig,
    config_from_dict,
    config_to_dict,
    load_config,
)
from slidecal.routines.ops.faults import CONTROLLER, FaultInjector
from slidecal.routines.plan import tool_pose
from slidecal.routines.run import RunRequest, run_calibration
from slidecal.routines.session import dump_yaml, transform_to_dict, write_atomic
from slidecal.routines.solve import RunOutcome
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import T_from_Rt
from slidecal.solver.problem import MOUNTS

help = "rehearse the cell's routine through the real ur-rtde client on a loopback controller"
REHEARSAL_FILE = "rehearsal.yaml"
#: The rehearsal's stale-data limit (a Python loopback goes unscheduled under load far longer than
#: a controller's cycle); three times the longest gap it showed before the run if that is longer.
LOOPBACK_STALE_S = 1.0


class LoopbackController:
    """The loopback controller process and its control channel (stdin/stdout JSON lines)."""

    def __init__(self, options: list[str], host: str | None = None) -> None:
        self.host = host or f"127.{os.getpid() % 250 + 1}.{np.random.default_rng().integers(250)}.1"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "slidecal.mocks.ur_controller", "--host", self.host,
             *options],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        )
        first = self._read(20.0)
        if "error" in first:
            self.stop()
            raise HardwareFault(f"the loopback controller did not start: {first['error']}")

    def _read(self, timeout_s: float) -> dict[str, Any]:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            self.stop()
            raise HardwareFault(
                f"the loopback controller stopped answering (exit code {self.proc.poll()})"
            )
        return json.loads(line)

    def ctl(self, command: str, answer: bool = True) -> dict[str, Any]:
        """Send one control command, return its JSON answer (``answer`` False: none awaited)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        return self._read(5.0) if answer else {}

    def true_tcp_pose(self) -> np.ndarray:
        """The arm's true ``T_base_tool`` (4, 4), metres (what the cameras see)."""
        return T_from_ur_pose(self.ctl("state")["tcp_pose"])

    def stop(self) -> None:
        """Quit the controller process (killed if it does not exit within 5 s)."""
        if self.proc.poll() is None:
            try:
                self.ctl("quit", answer=False)
                self.proc.wait(5.0)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(5.0)


#: Horizontal field of view assumed for a real cell's cameras in its twin (degrees).
TWIN_HFOV_DEG = 60.0


def simulated_twin(cfg: CellConfig) -> CellConfig:
    """The simulated cell standing in for a real one in a rehearsal: its robot, target, mount and
    cameras' names and sizes, ``approximate`` taken as the truth. ``InputError`` when the cell
    gives too little (several cameras that are not an OAK's left/right/rgb)."""
    given = config_to_dict(cfg)
    # the twin's board is simulated, so exact; its camera plans with the simulated camera's
    # noise unless the cell sets one other than the real camera's default
    given["target"] = {k: v for k, v in given["target"].items()
                       if k not in ("flatness_mm", "print_tolerance")}
    if cfg.plan.corner_noise_px == REAL_CORNER_NOISE_PX:
        del given["plan"]["corner_noise_px"]
    robot = {k: v for k, v in given["robot"].items()
             if k not in ("driver", "host", "take_control", "payload")}
    robot["driver"] = "simulated"
    names = [c.name for c in cfg.cameras]
    sim: dict[str, Any] = {"seed": 0}
    if cfg.camera_driver == "oak" and set(names) <= {"left", "right", "rgb"}:
        sim["camera_preset"] = "oak_d_like"
    elif len(names) == 1:
        c = cfg.cameras[0]
        f_px = c.width / 2.0 / np.tan(np.radians(TWIN_HFOV_DEG) / 2.0)
        K = [[f_px, 0.0, c.width / 2.0], [0.0, f_px, c.height / 2.0], [0.0, 0.0, 1.0]]
        sim["cameras"] = {c.name: {"width": c.width, "height": c.height, "K": K,
                                   "distortion": [0.0] * 5}}
    else:
        raise InputError(
            f"cameras {names}: a rehearsal cannot invent the extrinsics of several cameras; "
            "rehearse a copy of the cell with one camera, or a simulated cell",
            where=f"{cfg.source}: cameras.list",
        )
    frames = MOUNTS["eye_in_hand" if cfg.mount == "eye_in_hand" else "eye_to_hand"]
    sim[frames.hand_eye] = transform_to_dict(cfg.approx_T_hand_eye)
    sim[frames.target] = transform_to_dict(cfg.approx_T_target)
    if "start_q" not in robot and "start_pose" not in robot:
        # the camera at the stand-off, looking straight at the middle of the target
        pts = np.asarray(cfg.target.points_m, dtype=float)
        mid = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        T_base_tool = tool_pose(cfg, T_from_Rt(np.eye(3), [0.0, 0.0, cfg.standoff_m] - mid))
        if not urk.reachable(T_base_tool, None, urk.model_by_name(cfg.robot.model),
                             cfg.robot.tcp):
            raise InputError(
                "the pose that puts the camera at the stand-off over the target is out of "
                "reach of the arm; check approximate and standoff_m, or give robot.start_q",
                where=f"{cfg.source}: approximate",
            )
        robot["start_pose"] = ur_pose_from_T(T_base_tool)
    twin = {**given, "robot": robot, "simulation": sim,
            "cameras": {"driver": "simulated", "reference": cfg.reference_camera}}
    return config_from_dict(twin, f"{cfg.source} (simulated twin)")


def rehearse(
    config: str | Path | None = None,
    out_dir: str | Path | None = None,
    faults: list[str] | None = None,
    polyscope: str = "5.12",
    speed_slider: float = 1.0,
    progress: bool | None = None,
    recording: bool = False,
    seed: int | None = None,
) -> RunOutcome:
    """Run the cell's routine against the loopback controller; returns the ``RunOutcome``, raises
    as :func:`~slidecal.routines.run.run_calibration`."""
    cfg = load_config(config)
    driver_options: dict[str, Any] = {}
    if not cfg.simulated:
        driver_options = cfg.robot.ur_options
        cfg = simulated_twin(cfg)
    assert cfg.simulation is not None
    cell = SimulatedCell.from_config(cfg, seed)
    sim = cfg.simulation
    options = [
        "--model", cfg.robot.model, "--polyscope", polyscope,
        "--speed-slider", str(speed_slider),
        "--start-q=" + ",".join(f"{v:.17g}" for v in cell.robot.q),
        "--noise-mm", str(sim.robot_noise_m * 1000.0), "--noise-deg", str(sim.robot_noise_deg),
        "--seed", str(cell.seed),
    ]
    out = new_session_dir(out_dir)
    controller = LoopbackController(options)
    stale_s = max(LOOPBACK_STALE_S, 3.0 * controller.ctl("state").get("cycle_gap_max_s", 0.0))
    robot = URRobot(
        controller.host,
        max_speed_mps=cfg.robot.speed_mps,
        max_accel_mps2=cfg.robot.accel_mps2,
        tcp=cfg.robot.tcp,
        model=cfg.robot.model,
        frequency=125.0,
        stale_timeout_s=stale_s,
        **driver_options,
    )
    # the simulated cameras render from the controller's arm, not the simulated one
    cell.robot.true_pose = controller.true_tcp_pose  # type: ignore[method-assign]
    injector = None
    if faults:
        injector = FaultInjector(faults, lambda kind: controller.ctl(CONTROLLER[kind]), cell.rig)
    rig_cell = SimpleNamespace(robot=robot, rig=cell.rig, truth=cell.truth)
    report: dict[str, Any] = {"controller_options": options, "faults": list(faults or []),
                              "stale_limit_s": stale_s}
    state: dict[str, Any] = {}
    try:
        return run_calibration(RunRequest(
            cfg, out_dir=out, progress=progress, recording=recording, cell=rig_cell,
            faults=injector,
        ))
    except HardwareFault as e:
        state = _state(controller)
        gap_s = state.get("cycle_gap_max_s", 0.0)
        if gap_s >= stale_s:
            raise HardwareFault(
                f"{e}. The loopback controller itself went {gap_s:.2f} s unscheduled (this "
                f"host's CPU load; the rehearsal allows {stale_s:.2f} s): not the driver's "
                "fault; rehearse again on a less busy machine"
            ) from None
        raise
    finally:
        state = state or _state(controller)
        controller.stop()
        report["controller"] = robot.controller_info
        report["controller_events"] = state.get("events", [])
        report["arm_at_rest"] = not state.get("moving", True) and not state.get("stalled")
        report["controller_cycle_gap_max_s"] = state.get("cycle_gap_max_s")
        if out.is_dir():
            write_atomic(out / REHEARSAL_FILE, dump_yaml(report))


def _state(controller: LoopbackController) -> dict[str, Any]:
    try:
        return controller.ctl("state")
    except HardwareFault:
        return {}


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``slidecal rehearse`` options."""
    p.add_argument("--config", help="a cell file, real or simulated (default: the default cell)")
    p.add_argument("--out", help="session directory to create (default: sessions/<time>)")
    p.add_argument("--fault", action="append", metavar="KIND@FRAME",
                   help="inject a hardware fault (see slidecal.routines.ops.faults)")
    p.add_argument("--polyscope", default="5.12", help="controller version: 3.15 5.5 5.9 5.12")
    p.add_argument("--speed-slider", type=float, default=1.0, help="pendant speed slider 0-1")
    p.add_argument("--seed", type=int, help="the simulated cell's random seed")
    p.add_argument("--recording", action="store_true", help="write recording.rrd")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def main(args: argparse.Namespace) -> int:
    """Run the rehearsal and print its summary."""
    outcome = rehearse(
        args.config, args.out, args.fault, args.polyscope, args.speed_slider,
        progress=False if args.quiet else None, recording=args.recording, seed=args.seed,
    )
    if not args.quiet:
        print(outcome.summary, end="")
        print(f"rehearsal: {outcome.session_dir}  ({outcome.n_frames} frames, "
              f"{outcome.wall_time_s:.1f} s)")
    return 0

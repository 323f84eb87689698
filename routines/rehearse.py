"""Rehearse a cell's calibration through the real ur-rtde client (``slidecal rehearse``).

``slidecal rehearse [--config CELL] [--out DIR] [--fault KIND@FRAME] [--polyscope V]
[--speed-slider X]`` starts the loopback UR controller (``slidecal.mocks.ur_controller``) in
its own process on a loopback address of its own, connects the real UR driver
(:class:`~slidecal.drivers.ur.URRobot`, i.e. ur-rtde) to it, and runs the cell's routine
(:func:`~slidecal.routines.run.run_calibration`: plan, reachability checks, moves, captures,
solve) with the cell's simulated cameras rendering the target from the controller's true TCP
pose. The controller reports that pose with the cell's simulated robot error
(``simulation.noise``), drawn once per rest pose. Nothing leaves the machine; no robot moves.

The cell must be a simulated one (``robot.driver: simulated``, e.g. the default cell): its
``simulation`` block is the truth the cameras render. The session gets, besides what
``slidecal run`` writes, ``rehearsal.yaml``: what the controller said it was
(:attr:`URRobot.controller_info`) and what it saw (its events, the final arm state).
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

from slidecal.drivers.ur_pose import T_from_ur_pose
from slidecal.solver.errors import HardwareFault, InputError

help = "rehearse the cell's routine through the real ur-rtde client on a loopback controller"
REHEARSAL_FILE = "rehearsal.yaml"
#: The controller's state after the last rehearsal in this process (the fault table reads it).
LAST_CONTROLLER_STATE: dict[str, Any] = {}


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

    def ctl(self, command: str) -> dict[str, Any]:
        """Send one control command, return its JSON answer."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        return self._read(5.0)

    def true_tcp_pose(self) -> np.ndarray:
        """The arm's true ``T_base_tool`` (4, 4), metres (what the cameras see)."""
        return T_from_ur_pose(self.ctl("state")["tcp_pose"])

    def stop(self) -> None:
        """Quit the controller process (killed if it does not exit within 5 s)."""
        if self.proc.poll() is None:
            try:
                assert self.proc.stdin is not None
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(5.0)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait(5.0)


def rehearse(
    config: str | Path | None = None,
    out_dir: str | Path | None = None,
    faults: list[str] | None = None,
    polyscope: str = "5.12",
    speed_slider: float = 1.0,
    progress: bool | None = None,
    recording: bool = False,
    seed: int | None = None,
) -> Any:
    """Run the cell's routine against the loopback controller; returns the ``RunOutcome``.

    Raises like :func:`~slidecal.routines.run.run_calibration` (``HardwareFault`` after an
    injected fault, with every frame before it in the session).
    """
    from slidecal.drivers.ur import URRobot
    from slidecal.mocks.cell import SimulatedCell
    from slidecal.routines.config import load_config
    from slidecal.routines.faults import CONTROLLER, FaultInjector
    from slidecal.routines.run import default_session_dir, run_calibration
    from slidecal.routines.session import dump_yaml, write_atomic

    cfg = load_config(config)
    if not cfg.simulated or cfg.simulation is None:
        raise InputError(
            "rehearse needs a simulated cell (robot.driver: simulated) whose simulation block "
            "is the truth the cameras render; copy the cell and set its robot and cameras to "
            "simulated",
            where=f"{cfg.source}: robot.driver",
        )
    cell = SimulatedCell.from_config(cfg, seed)
    sim = cfg.simulation
    options = [
        "--model", cfg.robot.model, "--polyscope", polyscope,
        "--speed-slider", str(speed_slider),
        "--start-q=" + ",".join(f"{v:.17g}" for v in cell.robot.q),
        "--noise-mm", str(sim.robot_noise_m * 1000.0), "--noise-deg", str(sim.robot_noise_deg),
        "--seed", str(cell.seed),
    ]
    out = Path(out_dir) if out_dir is not None else default_session_dir()
    controller = LoopbackController(options)
    robot = URRobot(
        controller.host,
        max_speed_mps=cfg.robot.speed_mps,
        max_accel_mps2=cfg.robot.accel_mps2,
        tcp=cfg.robot.tcp,
        model=cfg.robot.model,
        frequency=125.0,
    )
    # the simulated cameras render from the controller's arm, not the simulated one
    cell.robot.true_pose = controller.true_tcp_pose  # type: ignore[method-assign]
    injector = None
    if faults:
        injector = FaultInjector(faults, lambda kind: controller.ctl(CONTROLLER[kind]), cell.rig)
    rig_cell = SimpleNamespace(robot=robot, rig=cell.rig, truth=cell.truth)
    report: dict[str, Any] = {"controller_options": options, "faults": list(faults or [])}
    try:
        outcome = run_calibration(
            cfg, out_dir=out, progress=progress, recording=recording, cell=rig_cell,
            faults=injector,
        )
        return outcome
    finally:
        try:
            state = controller.ctl("state")
        except HardwareFault:
            state = {}
        controller.stop()
        LAST_CONTROLLER_STATE.clear()
        LAST_CONTROLLER_STATE.update(state)
        report["controller"] = robot.controller_info
        report["controller_events"] = state.get("events", [])
        report["arm_at_rest"] = not state.get("moving", True) and not state.get("stalled")
        if out.is_dir():
            write_atomic(out / REHEARSAL_FILE, dump_yaml(report))


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``slidecal rehearse`` options."""
    p.add_argument("--config", help="a simulated cell file (default: the default cell)")
    p.add_argument("--out", help="session directory to create (default: sessions/<time>)")
    p.add_argument("--fault", action="append", metavar="KIND@FRAME",
                   help="inject a hardware fault (see slidecal.routines.faults)")
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

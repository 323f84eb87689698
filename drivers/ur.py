"""A Universal Robots arm through ur-rtde (``Robot`` protocol of ``drivers/base.py``).

Built on ``rtde_control.RTDEControlInterface``, ``rtde_receive.RTDEReceiveInterface`` and
``dashboard_client.DashboardClient`` (ur-rtde >= 1.6). The traps of HARDWARE_NOTES.md are handled
here: ``moveL`` returns False instead of raising (we stop and raise ``HardwareFault`` saying why);
the receive interface keeps returning its last values after a lost connection (we check
``isConnected()`` and that ``getTimestamp()`` advances before trusting a pose); no automatic
protective-stop recovery (an unattended calibration stops and reports). Every pose goes through
:mod:`slidecal.drivers.ur_pose`. The ur-rtde modules are imported in :meth:`URRobot.connect`, so
this module imports without them.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.drivers.ur_pose import T_from_ur_pose, pendant_text, ur_pose_from_T
from slidecal.solver.errors import HardwareFault, InputError

ROBOT_MODE_RUNNING = 7
SAFETY_MODE_NORMAL = 1

#: Safety modes (``getSafetyMode``) and what the operator should do about them.
SAFETY_MODES: dict[int, str] = {
    1: "normal",
    2: "reduced mode",
    3: "protective stop: check the cell for a collision or a safety-limit violation, unlock it "
    "on the teach pendant, then restart the calibration",
    4: "recovery mode (a joint is outside its safety limits): jog it back on the pendant",
    5: "safeguard stop: close the safeguard (door, light curtain) and reset it",
    6: "system emergency stop: release the emergency stop and reset it on the pendant",
    7: "robot emergency stop: release the emergency-stop button and reset it on the pendant",
    8: "safety violation: restart the safety system from the pendant",
    9: "safety fault: restart the safety system from the pendant",
    10: "validate joint id: confirm the joint ids on the pendant",
    11: "undefined safety mode: restart the controller",
    12: "automatic-mode safeguard stop: reset the safeguard",
    13: "three-position enabling stop: hold the enabling device or switch mode",
}
ROBOT_MODES: dict[int, str] = {
    -1: "no controller",
    0: "disconnected",
    1: "confirm safety",
    2: "booting",
    3: "power off",
    4: "power on",
    5: "idle (brakes engaged)",
    6: "backdrive",
    7: "running",
    8: "updating firmware",
}


def _describe(T: np.ndarray) -> str:
    pose = ", ".join(f"{v:.4f}" for v in ur_pose_from_T(T))
    return f"[{pose}] ({pendant_text(T)})"


class URRobot:
    """A UR arm driven over RTDE.

    Parameters
    ----------
    hostname
        The controller's IP address or name.
    max_speed_mps, max_accel_mps2
        Largest TCP speed and acceleration a move may ask for.
    tcp
        ``T_flange_tcp`` (4, 4), metres, set on the controller at connect; None keeps the
        controller's TCP (then poses are of that TCP).
    frequency
        RTDE frequency in Hz; -1 is 500 Hz on e-Series, 125 Hz on CB3.
    model
        ``"UR5e"`` etc.: when given, :meth:`is_reachable` also rejects poses near a singularity
        of the controller's joint solution (``ur_kinematics.singularity``).
    stale_timeout_s
        How long ``getTimestamp()`` may stay unchanged before the data is called stale.
    arrival_tol_m
        Largest distance between the target and the measured pose after a completed move.
    """

    def __init__(
        self,
        hostname: str,
        *,
        max_speed_mps: float = 0.25,
        max_accel_mps2: float = 1.2,
        tcp: np.ndarray | None = None,
        frequency: float = -1.0,
        model: str | None = None,
        stale_timeout_s: float = 0.1,
        settle_timeout_s: float = 5.0,
        arrival_tol_m: float = 1e-3,
    ) -> None:
        if not 0 < max_speed_mps <= 3.0:
            raise InputError(f"max_speed_mps must be in (0, 3] (ur-rtde's range): {max_speed_mps}")
        if not 0 < max_accel_mps2 <= 150.0:
            raise InputError(f"max_accel_mps2 must be in (0, 150], got {max_accel_mps2}")
        self.hostname = hostname
        self.max_speed_mps = float(max_speed_mps)
        self.max_accel_mps2 = float(max_accel_mps2)
        self.tcp = None if tcp is None else np.asarray(tcp, dtype=float)
        self.frequency = float(frequency)
        self.model = None if model is None else urk.model_by_name(model)
        self.stale_timeout_s = float(stale_timeout_s)
        self.settle_timeout_s = float(settle_timeout_s)
        self.arrival_tol_m = float(arrival_tol_m)
        self._control: Any = None
        self._receive: Any = None
        self._dashboard: Any = None
        self._last_timestamp = -np.inf

    # ---------------------------------------------------------------------------- connection
    def connect(self) -> None:
        """Connect; raise ``HardwareFault`` unless the robot is running in normal safety mode."""
        try:
            import dashboard_client
            import rtde_control
            import rtde_receive
        except ImportError as e:
            raise HardwareFault(
                f"ur-rtde is not importable ({e}); install it with 'pip install ur-rtde>=1.6'"
            ) from None
        where = f"robot at {self.hostname}"
        try:
            self._receive = rtde_receive.RTDEReceiveInterface(self.hostname, self.frequency)
        except RuntimeError as e:
            raise HardwareFault(
                f"cannot connect to the {where} over RTDE (port 30004): {e}; check the network "
                "and that the controller is on"
            ) from None
        try:
            self._dashboard = dashboard_client.DashboardClient(self.hostname)
            self._dashboard.connect()
        except RuntimeError:
            self._dashboard = None  # diagnostics only; the dashboard port may be firewalled
        robot_mode = int(self._receive.getRobotMode())
        if robot_mode != ROBOT_MODE_RUNNING:
            self.close()
            raise HardwareFault(
                f"{where} is not ready: robot mode {robot_mode} "
                f"({ROBOT_MODES.get(robot_mode, 'unknown')}); power it on and release the brakes "
                "on the teach pendant"
            )
        safety_mode = int(self._receive.getSafetyMode())
        if safety_mode != SAFETY_MODE_NORMAL:
            self.close()
            raise HardwareFault(
                f"{where} is not in normal safety mode: {safety_mode} "
                f"({SAFETY_MODES.get(safety_mode, 'unknown')})"
            )
        if self._dashboard is not None and not self._dashboard.isInRemoteControl():
            self.close()
            raise HardwareFault(
                f"{where} is in local control; switch it to remote control on the teach pendant"
            )
        try:
            self._control = rtde_control.RTDEControlInterface(self.hostname, self.frequency)
        except RuntimeError as e:
            self.close()
            raise HardwareFault(
                f"cannot open RTDE control of the {where}: {e}; check that it is in remote "
                "control and that no other program controls it"
            ) from None
        if self.tcp is not None and not self._control.setTcp(ur_pose_from_T(self.tcp)):
            self.close()
            raise HardwareFault(f"the {where} refused the TCP offset {ur_pose_from_T(self.tcp)}")
        self._last_timestamp = -np.inf
        self._fresh()

    def close(self) -> None:
        """Stop the control script and disconnect (idempotent); never moves the robot.

        The script is stopped only over a live link: after a lost connection ur-rtde's
        ``stopScript`` waits on the last received runtime state, i.e. up to 300 s.
        """
        control, receive, dashboard = self._control, self._receive, self._dashboard
        live = self._link_alive()
        self._control = self._receive = self._dashboard = None
        control_methods = ("stopScript", "disconnect") if live else ("disconnect",)
        for obj, methods in ((control, control_methods), (receive, ("disconnect",))):
            if obj is None:
                continue
            for m in methods:
                try:
                    getattr(obj, m)()
                except RuntimeError:
                    pass
        if dashboard is not None:
            try:
                dashboard.disconnect()
            except RuntimeError:
                pass

    # ------------------------------------------------------------------------------ checking
    def _require(self) -> None:
        if self._receive is None or self._control is None:
            raise HardwareFault(f"robot at {self.hostname} not connected: call connect() first")

    def _fresh(self) -> None:
        """Raise ``HardwareFault`` unless the receive data is live (connected, clock advancing)."""
        r = self._receive
        if not r.isConnected():
            raise HardwareFault(
                f"lost the RTDE connection to the robot at {self.hostname} (its pose data is "
                "stale); check the network cable and the controller, then reconnect"
            )
        deadline = time.monotonic() + self.stale_timeout_s
        while True:
            t = float(r.getTimestamp())
            if t > self._last_timestamp:
                self._last_timestamp = t
                return
            if time.monotonic() > deadline:
                raise HardwareFault(
                    f"the robot at {self.hostname} sent no new data for {self.stale_timeout_s} s "
                    f"(controller timestamp stuck at {t:.3f} s); the pose would be stale: check "
                    "the network and the controller, then reconnect"
                )
            time.sleep(0.002)

    def _link_alive(self) -> bool:
        """Both interfaces connected and the controller's clock still advancing: only then can
        a command be sent without ur-rtde waiting up to 300 s for an answer (measured: a silent
        link keeps ``isConnected()`` True, so the clock is what tells)."""
        if self._control is None or self._receive is None:
            return False
        try:
            if not (self._control.isConnected() and self._receive.isConnected()):
                return False
            self._fresh()
        except (HardwareFault, RuntimeError):
            return False
        return True

    def _diagnose(self, what: str) -> str:
        """A message saying why ``what`` failed, from the robot's state."""
        try:
            if not self._receive.isConnected() or not self._control.isConnected():
                return f"{what}: the connection to the robot was lost; check it and reconnect"
            safety = int(self._receive.getSafetyMode())
            robot_mode = int(self._receive.getRobotMode())
        except RuntimeError as e:
            return f"{what}: the robot did not answer ({e}); check the connection"
        if safety != SAFETY_MODE_NORMAL:
            return f"{what}: {SAFETY_MODES.get(safety, f'safety mode {safety}')}"
        if robot_mode != ROBOT_MODE_RUNNING:
            return (
                f"{what}: robot not ready (mode {robot_mode}, "
                f"{ROBOT_MODES.get(robot_mode, 'unknown')}); power it on and release the brakes"
            )
        return (
            f"{what}: the control script stopped, was not ready within 3 s or the move took "
            "over 300 s; check the pendant for a message and that the robot is in remote control"
        )

    # ------------------------------------------------------------------------ Robot protocol
    def measured_pose(self) -> np.ndarray:
        """``T_base_tool`` (4, 4), metres, of the configured TCP, from live data only."""
        self._require()
        self._fresh()
        return T_from_ur_pose(self._receive.getActualTCPPose())

    def move_linear(self, T_base_tool: np.ndarray, speed_mps: float, accel_mps2: float) -> None:
        """``moveL`` to ``T_base_tool`` (4, 4), metres; returns on arrival, ``HardwareFault`` on
        failure.

        The move is sent asynchronously and watched here (live pose, safety mode, a deadline
        from the trapezoidal move time): a blocking ``moveL`` whose connection drops waits up to
        300 s inside ur-rtde (measured against tests/ur_fake_controller.py), which an
        unattended cell cannot afford.
        """
        self._require()
        if not 0 < speed_mps <= self.max_speed_mps:
            raise InputError(f"speed_mps must be in (0, {self.max_speed_mps}], got {speed_mps}")
        if not 0 < accel_mps2 <= self.max_accel_mps2:
            raise InputError(f"accel_mps2 must be in (0, {self.max_accel_mps2}], got {accel_mps2}")
        T = np.asarray(T_base_tool, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError(f"move_linear needs a finite 4x4 T_base_tool, got shape {T.shape}")
        T_start = self.measured_pose()
        what = f"moveL to {_describe(T)} failed"
        try:
            ok = self._control.moveL(ur_pose_from_T(T), float(speed_mps), float(accel_mps2), True)
        except RuntimeError as e:
            self.stop()
            raise HardwareFault(f"{self._diagnose(what)} ({e})") from None
        if not ok:
            self.stop()
            raise HardwareFault(self._diagnose(what))
        d = float(np.linalg.norm(T[:3, 3] - T_start[:3, 3]))
        expected_s = d / speed_mps + speed_mps / accel_mps2
        t0 = time.monotonic()
        deadline = t0 + 2.0 * expected_s + self.settle_timeout_s
        while True:
            try:
                T_now = self.measured_pose()  # live data or HardwareFault
                safety = int(self._receive.getSafetyMode())
                speed = np.asarray(self._receive.getActualTCPSpeed(), dtype=float)
            except HardwareFault:
                self.stop()
                raise
            if safety != SAFETY_MODE_NORMAL:
                self.stop()
                raise HardwareFault(self._diagnose(what))
            miss = float(np.linalg.norm(T_now[:3, 3] - T[:3, 3]))
            at_rest = np.linalg.norm(speed[:3]) < 1e-3 and np.linalg.norm(speed[3:]) < 1e-3
            if at_rest and miss <= self.arrival_tol_m:
                return
            now = time.monotonic()
            if at_rest and now - t0 > expected_s + 0.2 or now > deadline:
                self.stop()
                raise HardwareFault(
                    f"moveL to {_describe(T)} was accepted but the robot is "
                    f"{miss * 1000:.1f} mm away, at {_describe(T_now)}, "
                    + ("at rest" if at_rest else f"still moving after {now - t0:.1f} s")
                    + "; check the pendant and the TCP setting"
                )
            time.sleep(0.004)

    def wait_settled(self, settle_s: float) -> None:
        """Wait until the reported TCP speed is below 1 mm/s, then ``settle_s`` for vibrations."""
        self._require()
        if settle_s < 0:
            raise InputError(f"settle_s must not be negative, got {settle_s}")
        deadline = time.monotonic() + self.settle_timeout_s
        while True:
            self._fresh()
            speed = np.asarray(self._receive.getActualTCPSpeed(), dtype=float)
            if np.linalg.norm(speed[:3]) < 1e-3 and np.linalg.norm(speed[3:]) < 1e-3:
                break
            if time.monotonic() > deadline:
                self.stop()
                raise HardwareFault(
                    f"the robot at {self.hostname} still moves after {self.settle_timeout_s} s "
                    f"(TCP speed {np.linalg.norm(speed[:3]) * 1000:.1f} mm/s); check the pendant"
                )
            time.sleep(0.01)
        time.sleep(settle_s)

    def stop(self) -> None:
        """``stopL``: decelerate the tool to rest. Safe at any time, also when not connected.

        Over a lost link nothing can be sent: ur-rtde's ``stopL`` would then wait up to 300 s
        (measured), so it is skipped; the controller finishes the move it was given (a planned,
        checked pose) and stops there.
        """
        if not self._link_alive():
            return
        try:
            self._control.stopL(10.0)
        except RuntimeError:
            pass  # connection gone while stopping

    def is_reachable(self, T_base_tool: np.ndarray) -> bool:
        """Controller IK near the current joints succeeds and the pose is within safety limits.

        ``getInverseKinematicsHasSolution`` is asked first: URScript's ``get_inverse_kin``
        raises on an unreachable pose and stops the control script, so the next move would
        fail (found with the real client against tests/ur_fake_controller.py). It needs
        PolyScope 5.10 / 3.15 or newer.
        """
        self._require()
        pose = ur_pose_from_T(np.asarray(T_base_tool, dtype=float))
        self._fresh()
        q_near = list(self._receive.getActualQ())
        if not self._control.getInverseKinematicsHasSolution(pose, q_near):
            return False
        q = self._control.getInverseKinematics(pose, q_near)
        if len(q) != 6:
            return False
        if not self._control.isPoseWithinSafetyLimits(pose):
            return False
        return self.model is None or urk.singularity(np.asarray(q), self.model) is None

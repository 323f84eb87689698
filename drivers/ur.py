"""A Universal Robots arm through ur-rtde (``Robot`` protocol of ``drivers/base.py``).

The order of the connection's checks, what is refused, how the client's traps are handled and
when ur-rtde is imported: docs/DRIVERS.md."""

from __future__ import annotations

import re
import socket
import struct
import time
from contextlib import suppress
from typing import Any

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.drivers.base import checked_move
from slidecal.drivers.ur_pose import T_from_ur_pose, describe, ur_pose_from_T
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import rvec_from_R

ROBOT_MODE_RUNNING = 7
#: Safety modes in which the arm works normally: normal, and reduced (lower speed limits).
SAFETY_MODES_OK = (1, 2)
DASHBOARD_PORT, RTDE_PORT = 29999, 30004
#: RTDE runtime states (``getRuntimeState``); only STOPPED means no program would be ended.
RUNTIME_STATES = {0: "stopping", 1: "stopped", 2: "playing", 3: "pausing", 4: "paused",
                  5: "resuming"}
RUNTIME_STOPPED = 1
#: The program name of ur-rtde's control script (its ``def``), as the dashboard reports it.
LEFTOVER_SCRIPT = "rtde_control"

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


def parse_version(text: str) -> tuple[int, ...] | None:
    """``(major, minor, bugfix[, build])`` from a PolyScope version line, None if it holds none."""
    m = re.search(r"(\d+)\.(\d+)\.(\d+)(?:\.(\d+))?", text or "")
    return None if m is None else tuple(int(g) for g in m.groups() if g is not None)


def has_ik_query(version: tuple[int, ...]) -> bool:
    """Whether ur-rtde's script holds ``get_inverse_kin_has_solution`` (PolyScope 5.10+, 3.15+)."""
    major, minor = version[0], version[1]
    return (major == 3 and minor >= 15) or (major == 5 and minor >= 10) or major > 5


def _recv_exactly(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionResetError("closed by the controller")
        data += chunk
    return data


def _rtde_answer(sock: socket.socket, request: bytes) -> bytes:
    """Send an RTDE request, return the answer's payload."""
    sock.sendall(request)
    size, _ = struct.unpack(">HB", _recv_exactly(sock, 3))
    return _recv_exactly(sock, size - 3)


def probe_controller(host: str, timeout_s: float) -> tuple[int, int, int, int]:
    """Check within ``timeout_s`` (per port) that ``host`` answers as a UR controller (dashboard
    welcome line, RTDE protocol 2) with plain sockets, before ur-rtde's blocking constructors;
    returns the controller version ``(major, minor, bugfix, build)``. ``HardwareFault`` saying which
    port did what."""
    where = f"the robot controller at {host}"

    def fail(port: int, e: BaseException) -> HardwareFault:
        if isinstance(e, TimeoutError | socket.timeout):
            why = f"no answer within {timeout_s:g} s"
        elif isinstance(e, ConnectionRefusedError):
            why = "connection refused"
        else:
            why = str(e) or type(e).__name__
        return HardwareFault(
            f"{where} is not reachable on port {port} ({why}); check the address in the cell "
            "file, the network cable and that the controller is switched on and booted"
        )

    try:
        with socket.create_connection((host, DASHBOARD_PORT), timeout=timeout_s) as s:
            s.settimeout(timeout_s)
            while _recv_exactly(s, 1) != b"\n":  # the welcome line
                pass
    except OSError as e:
        raise fail(DASHBOARD_PORT, e) from None
    try:
        with socket.create_connection((host, RTDE_PORT), timeout=timeout_s) as s:
            s.settimeout(timeout_s)
            accepted = _rtde_answer(s, struct.pack(">HBH", 5, ord("V"), 2))
            if not accepted or accepted[0] != 1:
                raise HardwareFault(
                    f"{where} refused RTDE protocol version 2; it needs PolyScope 3.10 / 5.0 or "
                    "newer"
                )
            payload = _rtde_answer(s, struct.pack(">HB", 3, ord("v")))
            if len(payload) < 16:
                raise ConnectionResetError("short controller-version answer")
            return tuple(struct.unpack(">4I", payload[:16]))  # type: ignore[return-value]
    except OSError as e:
        raise fail(RTDE_PORT, e) from None


def cell_options(robot_section: Any) -> dict[str, Any]:
    """``URRobot`` keyword arguments from a cell file's ``robot:`` section (``take_control``,
    ``payload``, ``upper_range_registers``: docs/FORMATS.md)."""
    raw = dict(robot_section or {})
    out: dict[str, Any] = {}
    for key in ("take_control", "upper_range_registers"):
        out[key] = raw.get(key, False)
        if not isinstance(out[key], bool):
            raise InputError(f"must be true or false, got {out[key]!r}", where=f"robot.{key}")
    payload = raw.get("payload")
    if payload is not None:
        if not isinstance(payload, dict) or "mass_kg" not in payload or set(payload) - {
            "mass_kg", "cog_m"
        }:
            raise InputError(
                f"must be {{mass_kg: M, cog_m: [x, y, z]}} (cog_m optional), got {payload!r}",
                where="robot.payload",
            )
        try:
            out["payload_kg"] = float(payload["mass_kg"])
        except (TypeError, ValueError):
            raise InputError(f"must be a number in kg, got {payload['mass_kg']!r}",
                             where="robot.payload.mass_kg") from None
        out["payload_cog_m"] = payload.get("cog_m")
    return out


def _at_rest(tcp_speed: np.ndarray) -> bool:
    """Below 1 mm/s and 1 mrad/s."""
    return bool(np.linalg.norm(tcp_speed[:3]) < 1e-3 and np.linalg.norm(tcp_speed[3:]) < 1e-3)


class URRobot:
    """A UR arm driven over RTDE.

    ``hostname``: the controller's address. ``max_speed_mps``, ``max_accel_mps2``: the largest a
    move may ask for. ``tcp``: ``T_flange_tcp`` (4, 4) m set at connect (None: the controller's).
    ``frequency``: RTDE Hz (-1: 500 e-Series, 125 CB3). ``model``: ``"UR5e"`` etc.: also refuse
    poses near a singularity. ``stale_timeout_s``: how long ``getTimestamp()`` may stand still.
    ``arrival_tol_m``, ``arrival_tol_deg``: both must hold after a move. ``take_control``: consent
    to stop a running program. ``payload_kg``, ``payload_cog_m`` (3,) m flange frame: set at connect
    (None keeps the controller's centre of gravity). ``upper_range_registers``: RTDE input registers
    24-47. ``connect_timeout_s``: per port at connect.
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
        arrival_tol_deg: float = 0.1,
        take_control: bool = False,
        payload_kg: float | None = None,
        payload_cog_m: np.ndarray | list[float] | None = None,
        connect_timeout_s: float = 3.0,
        upper_range_registers: bool = False,
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
        self.arrival_tol_deg = float(arrival_tol_deg)
        self.take_control = bool(take_control)
        if payload_kg is not None and not 0.0 <= float(payload_kg) <= 50.0:
            raise InputError(f"payload mass must be in [0, 50] kg, got {payload_kg}",
                             where="robot.payload.mass_kg")
        cog = None if payload_cog_m is None else np.asarray(payload_cog_m, dtype=float)
        if cog is not None and (cog.shape != (3,) or not np.all(np.isfinite(cog))):
            raise InputError(f"the payload's centre of gravity is 3 numbers in metres, got "
                             f"{payload_cog_m!r}", where="robot.payload.cog_m")
        if cog is not None and payload_kg is None:
            raise InputError("a payload centre of gravity needs its mass; add mass_kg",
                             where="robot.payload")
        self.payload_kg = None if payload_kg is None else float(payload_kg)
        self.payload_cog_m = cog
        self.connect_timeout_s = float(connect_timeout_s)
        self.upper_range_registers = bool(upper_range_registers)
        self.controller_info: dict[str, Any] = {}
        self._version: tuple[int, ...] = ()
        self._ik_on_controller = True
        self._T_flange_tcp = np.eye(4)
        self._control: Any = None
        self._receive: Any = None
        self._dashboard: Any = None
        self._last_timestamp = -np.inf

    # ---------------------------------------------------------------------------- connection
    def connect(self) -> None:
        """Connect (the order of checks: docs/DRIVERS.md); ``HardwareFault`` unless the robot runs
        in normal or reduced safety mode, takes remote commands, and nothing the user did not
        consent to would be stopped. Fills :attr:`controller_info` (None where it cannot say)."""
        try:
            import dashboard_client
            import rtde_control
            import rtde_receive
        except ImportError as e:
            raise HardwareFault(
                f"ur-rtde is not importable ({e}); install it with 'pip install ur-rtde>=1.6'"
            ) from None
        where = f"robot at {self.hostname}"
        try:  # every refusal below disconnects first
            running, program_state = self._ask_dashboard(dashboard_client, where)
            self._check_state(rtde_receive, where, running, program_state)
            self._open_control(rtde_control, where)
            self._set_tool(where)
        except BaseException:
            self.close()
            raise
        self._last_timestamp = -np.inf
        self._fresh()

    def _ask_dashboard(self, dashboard_client: Any, where: str) -> tuple[bool, str]:
        """The dashboard's answers (version, model, remote control, the program's state) into
        :attr:`controller_info`; whether a program runs, and its state."""
        rtde_version = probe_controller(self.hostname, self.connect_timeout_s)
        try:
            self._dashboard = dashboard_client.DashboardClient(self.hostname)
            self._dashboard.connect(int(self.connect_timeout_s * 1000))
            if not self._dashboard.isConnected():
                raise RuntimeError("no connection")
            version_text = str(self._dashboard.polyscopeVersion())
            model_text = str(self._dashboard.getRobotModel()).strip()
            program_state = str(self._dashboard.programState()).strip()
            running = bool(self._dashboard.running()) or program_state.upper().startswith(
                ("PLAYING", "PAUSED", "PAUSING", "RESUMING")
            )
        except RuntimeError as e:
            raise HardwareFault(
                f"the dashboard server of the {where} (port 29999) does not answer ({e}); "
                "check that the controller is booted and not in a pop-up"
            ) from None
        version = parse_version(version_text) or tuple(rtde_version)
        self._version = version
        try:
            serial = str(self._dashboard.getSerialNumber()).strip()
        except RuntimeError:
            serial = None  # PolyScope < 5.6 cannot say
        remote: bool | None = None
        if version[0] == 5 and version[1] >= 6:  # the dashboard says it (PolyScope 5.6+)
            try:
                remote = bool(self._dashboard.isInRemoteControl())
            except RuntimeError as e:  # the dashboard's socket failed (boost system_error)
                raise HardwareFault(
                    f"the dashboard server of the {where} (port 29999) stopped answering ({e}); "
                    "check the network and that the controller is not in a pop-up"
                ) from None
            if not remote:
                raise HardwareFault(
                    f"{where} is in local control; switch it to remote control on the teach "
                    "pendant"
                )
        if self.model is None and model_text.upper().startswith("UR"):
            name = model_text.split()[0] + ("e" if version[0] >= 5 else "")
            self.model = urk.MODELS.get(name.lower())
        self._ik_on_controller = has_ik_query(version)
        self.controller_info = {
            "polyscope_version": ".".join(str(v) for v in version),
            "controller_version": ".".join(str(v) for v in rtde_version),
            "robot_model": model_text,
            "serial_number": serial,
            "remote_control": remote,
            "ik_check": "controller" if self._ik_on_controller else "host",
            "program_state": program_state,
            "program_stopped": None,
        }
        return running, program_state

    def _check_state(
        self, rtde_receive: Any, where: str, running: bool, program_state: str
    ) -> None:
        """Open RTDE receive; refuse a robot not running, not in normal safety mode, or running
        a program the user did not let slidecal stop."""
        try:
            self._receive = rtde_receive.RTDEReceiveInterface(
                self.hostname, self.frequency, [], False, self.upper_range_registers
            )
        except RuntimeError as e:
            raise HardwareFault(
                f"cannot connect to the {where} over RTDE (port 30004): {e}; check the network "
                "and that the controller is on"
            ) from None
        robot_mode = int(self._receive.getRobotMode())
        if robot_mode != ROBOT_MODE_RUNNING:
            raise HardwareFault(
                f"{where} is not ready: robot mode {robot_mode} "
                f"({ROBOT_MODES.get(robot_mode, 'unknown')}); power it on and release the brakes "
                "on the teach pendant"
            )
        safety_mode = int(self._receive.getSafetyMode())
        if safety_mode not in SAFETY_MODES_OK:
            raise HardwareFault(
                f"{where} is not in normal safety mode: {safety_mode} "
                f"({SAFETY_MODES.get(safety_mode, 'unknown')})"
            )
        self.controller_info["safety_mode"] = SAFETY_MODES[safety_mode]
        self.controller_info["speed_slider"] = float(self._receive.getSpeedScalingCombined())
        runtime = int(self._receive.getRuntimeState())
        if runtime != RUNTIME_STOPPED and not running:
            running = True
            program_state = f"runtime state {RUNTIME_STATES.get(runtime, runtime)}"
            self.controller_info["program_state"] = program_state
        if running:
            if not self.take_control and LEFTOVER_SCRIPT in program_state.split():
                raise HardwareFault(
                    f"ur-rtde's control script ({program_state}) still runs on the {where}: "
                    "an earlier connection lost its link before it could stop it (no program of "
                    "yours is running). Press stop on the pendant, or allow slidecal to stop it "
                    "with 'take_control: true' in the cell file's robot section, then resume"
                )
            if not self.take_control:
                raise HardwareFault(
                    f"a program is running on the {where} ({program_state}); connecting would "
                    "stop it. Stop it on the pendant, or allow slidecal to stop it with "
                    "'take_control: true' in the cell file's robot section"
                )
            self.controller_info["program_stopped"] = program_state

    def _open_control(self, rtde_control: Any, where: str) -> None:
        """Open RTDE control (ur-rtde uploads its script), naming a fieldbus that holds the
        registers."""
        flags = rtde_control.RTDEControlInterface.Flags
        try:
            self._control = rtde_control.RTDEControlInterface(
                self.hostname, self.frequency, int(flags.FLAG_UPLOAD_SCRIPT) | (
                    int(flags.FLAG_UPPER_RANGE_REGISTERS) if self.upper_range_registers else 0)
            )
        except RuntimeError as e:
            if "already in use" in str(e):
                raise HardwareFault(
                    f"the RTDE input registers ur-rtde needs are taken on the {where}: "
                    "EtherNet/IP, PROFINET or a MODBUS unit in its installation uses them. "
                    "Switch that fieldbus off, or set 'upper_range_registers: true' in the cell "
                    "file's robot section (registers 24-47) if the fieldbus leaves those free"
                ) from None
            raise HardwareFault(
                f"cannot open RTDE control of the {where}: {e}; check that it is in remote "
                "control and that no other program controls it"
            ) from None

    def _set_tool(self, where: str) -> None:
        """The TCP offset (the cell's, or the controller's) and the payload."""
        if self.tcp is not None and not self._control.setTcp(ur_pose_from_T(self.tcp)):
            raise HardwareFault(f"the {where} refused the TCP offset {ur_pose_from_T(self.tcp)}")
        try:  # ur-rtde raises RuntimeError when the control script does not answer
            self._T_flange_tcp = (
                self.tcp if self.tcp is not None else T_from_ur_pose(self._control.getTCPOffset())
            )
        except (RuntimeError, ValueError) as e:
            raise HardwareFault(
                f"the {where} did not give its TCP offset ({e}); check the pendant for a "
                "message, or set robot.tcp in the cell file"
            ) from None
        if self.payload_kg is not None:
            cog = [] if self.payload_cog_m is None else [float(v) for v in self.payload_cog_m]
            if not cog and self._version[0] < 5:  # see payload_cog_m in the class docstring
                try:
                    cog = [float(v) for v in self._receive.getPayloadCog()]
                except RuntimeError:
                    cog = []
                if len(cog) != 3:
                    raise InputError(
                        f"PolyScope {self.controller_info['polyscope_version']} cannot keep the "
                        "payload's centre of gravity and did not report it; give cog_m",
                        where="robot.payload",
                    )
            if not self._control.setPayload(self.payload_kg, cog):
                raise HardwareFault(
                    f"the {where} refused the payload {self.payload_kg} kg at {cog} m; check "
                    "the values against the arm's rated payload"
                )
            self.controller_info["payload"] = {"mass_kg": self.payload_kg, "cog_m": cog or None}

    def close(self) -> None:
        """Stop the control script (over a live link only: ur-rtde's ``stopScript`` would wait 300 s
        on a lost one) and disconnect; idempotent, never moves the robot."""
        control, receive, dashboard = self._control, self._receive, self._dashboard
        live = self._link_alive()
        self._control = self._receive = self._dashboard = None
        calls = [(control, "stopScript")] if live else []
        calls += [(control, "disconnect"), (receive, "disconnect"), (dashboard, "disconnect")]
        for obj, method in calls:
            if obj is not None:
                with suppress(RuntimeError):
                    getattr(obj, method)()

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
        if safety not in SAFETY_MODES_OK:
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
        """``moveL`` to ``T_base_tool`` (4, 4), metres; returns on arrival (``arrival_tol_m`` and
        ``_deg``), ``HardwareFault`` on failure. Sent asynchronously and watched here: a blocking
        ``moveL`` waits up to 300 s over a dropped link."""
        self._require()
        T = checked_move(self, T_base_tool, speed_mps, accel_mps2)
        T_start = self.measured_pose()
        what = f"moveL to {describe(T)} failed"
        try:
            ok = self._control.moveL(ur_pose_from_T(T), float(speed_mps), float(accel_mps2), True)
        except RuntimeError as e:
            self.stop()
            raise HardwareFault(f"{self._diagnose(what)} ({e})") from None
        if not ok:
            self.stop()
            raise HardwareFault(self._diagnose(what))
        d = float(np.linalg.norm(T[:3, 3] - T_start[:3, 3]))
        angle = float(np.linalg.norm(rvec_from_R(T_start[:3, :3].T @ T[:3, :3])))
        full_speed_s = max(
            urk.trapezoid_time_s(d, speed_mps, accel_mps2),
            urk.trapezoid_time_s(angle, speed_mps, accel_mps2),
        )
        t0 = time.monotonic()
        slowest = 1.0
        while True:
            try:
                T_now = self.measured_pose()  # live data or HardwareFault
                safety = int(self._receive.getSafetyMode())
                speed = np.asarray(self._receive.getActualTCPSpeed(), dtype=float)
                slider = float(self._receive.getSpeedScalingCombined())
            except HardwareFault:
                self.stop()
                raise
            if safety not in SAFETY_MODES_OK:
                self.stop()
                raise HardwareFault(self._diagnose(what))
            slowest = min(slowest, max(slider, 0.01))
            expected_s = full_speed_s / slowest
            miss = float(np.linalg.norm(T_now[:3, 3] - T[:3, 3]))
            miss_deg = float(np.degrees(np.linalg.norm(rvec_from_R(T_now[:3, :3].T @ T[:3, :3]))))
            at_rest = _at_rest(speed)
            if at_rest and miss <= self.arrival_tol_m and miss_deg <= self.arrival_tol_deg:
                return
            now = time.monotonic()
            if (at_rest and now - t0 > expected_s + 0.2) or (
                now > t0 + 2.0 * expected_s + self.settle_timeout_s
            ):
                self.stop()
                raise HardwareFault(
                    f"moveL to {describe(T)} was accepted but the robot is "
                    f"{miss * 1000:.1f} mm and {miss_deg:.2f} deg away, at {describe(T_now)}, "
                    + ("at rest" if at_rest else f"still moving after {now - t0:.1f} s")
                    + f" (running at {slider:.0%} of the commanded speed: the pendant's slider "
                    "times the trajectory limiter); check the pendant and the TCP setting"
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
            if _at_rest(speed):
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
        """``stopL``: decelerate the tool to rest; safe at any time. Skipped over a lost link
        (ur-rtde would wait 300 s): the controller finishes its planned, checked move and stops
        there."""
        if not self._link_alive():
            return
        with suppress(RuntimeError):  # the connection gone while stopping
            self._control.stopL(10.0)

    def _script_answered(self, T: np.ndarray) -> None:
        """``HardwareFault`` when a "no" from the controller came from a stopped control script
        (ur-rtde answers False / [] then, as for an unreachable pose)."""
        if not self._control.isProgramRunning():
            raise HardwareFault(self._diagnose(f"the reachability query for {describe(T)} failed"))

    def is_reachable(self, T_base_tool: np.ndarray) -> bool:
        """An IK solution near the current joints, inside the joint and safety limits (which
        kinematics answer: docs/DRIVERS.md), not near a singularity when the model is known."""
        self._require()
        T = np.asarray(T_base_tool, dtype=float)
        pose = ur_pose_from_T(T)
        self._fresh()
        q_near = list(self._receive.getActualQ())
        try:
            if self._ik_on_controller:
                if not self._control.getInverseKinematicsHasSolution(pose, q_near):
                    return False
                q = self._control.getInverseKinematics(pose, q_near)
                if len(q) != 6:  # [] also when the control script stopped
                    self._script_answered(T)
                    return False
            else:
                if self.model is None:
                    raise HardwareFault(
                        f"PolyScope {self.controller_info.get('polyscope_version')} cannot check "
                        "reachability itself and the robot model is unknown; give robot.model "
                        "in the cell file (or update PolyScope to 5.10 / 3.15 or newer)"
                    )
                sols = urk.ik(T, np.asarray(q_near), self.model, self._T_flange_tcp)
                if not sols:
                    return False
                q = sols[0]
            if not self._control.isPoseWithinSafetyLimits(pose):
                self._script_answered(T)  # False also when the control script stopped
                return False
        except RuntimeError as e:
            raise HardwareFault(
                f"{self._diagnose(f'the reachability query for {describe(T)} failed')} ({e})"
            ) from None
        return self.model is None or urk.singularity(np.asarray(q), self.model) is None

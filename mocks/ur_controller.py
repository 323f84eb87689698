"""A loopback Universal Robots controller for the real ur-rtde client (tests and rehearsals).

Run as its own process (``python -m slidecal.mocks.ur_controller --help``): the ur-rtde
constructors hold the GIL while they block. Its ports, register protocol, modelled PolyScope
versions, arm model and stdin control channel: docs/DRIVERS.md.
"""


from __future__ import annotations

import argparse
import json
import os
import re
import select
import socket
import struct
import sys
import time

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.mocks.robot import interpolate_pose
from slidecal.solver.geometry import R_from_rvec, inv_T, rvec_from_R

HOST = "127.0.0.1"
RTDE_PORT, SCRIPT_PORT, DASHBOARD_PORT = 30004, 30003, 29999
#: The PolyScope versions modelled: RTDE controller version and the dashboard's version line.
VERSIONS: dict[str, tuple[tuple[int, int, int, int], str]] = {
    "3.15": ((3, 15, 7, 106331), "URSoftware 3.15.7.106331 (Jun 22 2021)"),
    "5.5": ((5, 5, 1, 83007), "URSoftware 5.5.1.83007 (Nov 11 2019)"),
    "5.9": ((5, 9, 4, 1031232), "URSoftware 5.9.4.1031232 (Jan 10 2021)"),
    "5.11": ((5, 11, 1, 108318), "URSoftware 5.11.1.108318 (Mar 22 2021)"),
    "5.12": ((5, 12, 2, 1101534), "URSoftware 5.12.2.1101534 (Feb 17 2022)"),
}
DEFAULT_VERSION = "5.12"
SERIAL_NUMBER = "20185500001"
Q0 = np.array([0.0, -1.9, 1.7, -1.37, -1.57, 0.0])
SAFETY_Z_MIN_M = 0.0
#: Between a move command being acknowledged and the arm starting to move, as on a controller
#: whose motion thread starts planning in a later cycle: the arm reports rest at the start pose.
MOTION_LATENCY_S = 0.03
SAFETY_MODE_NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY",
                     5: "SAFEGUARD_STOP", 6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP",
                     8: "VIOLATION", 9: "FAULT"}
#: The safety mode a ``pstop`` / ``estop`` move fault leaves and what the events call it.
SAFETY_STOPS = {"pstop": (3, "protective stop"), "estop": (7, "robot emergency stop")}
ROBOT_MODE_NAMES = {3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 7: "RUNNING"}
#: The control channel's ``WORD VALUE`` settings: the robot's attribute and the value's type.
SETTINGS = {"slider": ("speed_slider", float), "safety": ("safety_mode", int),
            "robotmode": ("robot_mode", int)}

# RTDE message types
V, v, O, I, S, P, U, M = (ord(c) for c in "VvOISPUM")
RUNTIME_STOPPED, RUNTIME_PLAYING = 1, 2
READY, DONE = 1, 2
MOVEL, SET_TCP, IK_ARGS, STOPL, IS_POSE_SAFE, IK_DEFAULT = 3, 29, 30, 33, 36, 46
SET_PAYLOAD, GET_TCP_OFFSET = 17, 40
IK_HAS_SOLUTION_DEFAULT, IK_HAS_SOLUTION_ARGS, STOP_SCRIPT = 60, 61, 255
SAFETY_BIT_NORMAL, SAFETY_BIT_REDUCED, SAFETY_BIT_PROTECTIVE = 1 << 0, 1 << 1, 1 << 2
SAFETY_BIT_ROBOT_ESTOP = 1 << 7
#: Script functions whose presence in the uploaded script decides whether a command works.
SCRIPT_FUNCTION = dict.fromkeys((IK_HAS_SOLUTION_DEFAULT, IK_HAS_SOLUTION_ARGS),
                                "get_inverse_kin_has_solution(")
STATUS_BIT_POWER_ON, STATUS_BIT_PROGRAM_RUNNING = 1 << 0, 1 << 1

FORMATS = {
    "DOUBLE": ">d", "VECTOR6D": ">6d", "VECTOR3D": ">3d", "INT32": ">i", "UINT32": ">I",
    "UINT64": ">Q", "VECTOR6INT32": ">6i", "VECTOR6UINT32": ">6I", "BOOL": ">?", "UINT8": ">B",
}
VECTOR6D_NAMES = (
    "target_q target_qd target_qdd target_current target_moment actual_q actual_qd actual_current "
    "joint_control_output actual_TCP_pose actual_TCP_speed actual_TCP_force target_TCP_pose "
    "target_TCP_speed joint_temperatures actual_joint_voltage ft_raw_wrench payload_inertia "
    "actual_current_as_torque external_force_torque"
).split()
DOUBLE_NAMES = (
    "timestamp actual_execution_time speed_scaling target_speed_fraction actual_momentum "
    "actual_main_voltage actual_robot_voltage actual_robot_current standard_analog_input0 "
    "standard_analog_input1 standard_analog_output0 standard_analog_output1 payload"
).split()
TYPES = {
    **{n: "VECTOR6D" for n in VECTOR6D_NAMES},
    **{n: "DOUBLE" for n in DOUBLE_NAMES},
    **{n: "VECTOR3D" for n in ("actual_tool_accelerometer", "payload_cog", "elbow_position",
                                "elbow_velocity")},
    "robot_mode": "INT32", "safety_mode": "INT32", "safety_status": "INT32",
    "joint_mode": "VECTOR6INT32", "runtime_state": "UINT32", "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32", "actual_digital_input_bits": "UINT64",
    "actual_digital_output_bits": "UINT64",
}
#: Output variables that are constant here: the joints in running mode, gravity, the supply, and
#: the trajectory limiter's factor (nothing limits a straight moveL).
CONSTANTS = {"joint_mode": [253] * 6, "actual_tool_accelerometer": [0.0, 0.0, 9.81],
             "actual_main_voltage": 48.0, "actual_robot_voltage": 48.0, "speed_scaling": 1.0}
#: Output variables that are one attribute of :class:`Robot`.
ATTRIBUTES = {"robot_mode": "robot_mode", "safety_mode": "safety_mode",
              "safety_status": "safety_mode", "runtime_state": "runtime_state",
              "target_speed_fraction": "speed_slider"}

#: An RTDE register's variable name.
REGISTER = re.compile(r"(input|output)_(int|double)_register_(\d+)")


def var_type(name: str) -> str:
    """The RTDE type of a variable name, ``NOT_FOUND`` when this fake does not know it."""
    if name in TYPES:
        return TYPES[name]
    m = REGISTER.fullmatch(name)
    return "NOT_FOUND" if m is None else "INT32" if m[2] == "int" else "DOUBLE"


def message(kind: int, payload: bytes = b"") -> bytes:
    """One RTDE message: header (uint16 size incl. the 3-byte header, uint8 type) + payload."""
    return struct.pack(">HB", 3 + len(payload), kind) + payload


class Robot:
    """The simulated arm, its controller's state and its control script's registers."""

    def __init__(self, version: str = DEFAULT_VERSION, model: str = "UR5e",
                 start_q: np.ndarray = Q0, speed_slider: float = 1.0, robot_mode: int = 7,
                 safety_mode: int = 1, remote: bool = True, program: str | None = None,
                 noise_m: float = 0.0, noise_deg: float = 0.0, seed: int = 0,
                 payload_cog: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 fieldbus: bool = False) -> None:
        if version not in VERSIONS:
            raise ValueError(f"unknown PolyScope version {version!r}; use one of {list(VERSIONS)}")
        self.version = version
        self.controller_version, self.polyscope_text = VERSIONS[version]
        self.model = urk.model_by_name(model)
        self.t0 = time.monotonic()
        self.q = np.asarray(start_q, dtype=float).copy()
        self.T_base_flange = urk.fk(self.q, self.model)
        self.T_flange_tcp = np.eye(4)
        self.speed = np.zeros(6)
        self.speed_slider = float(speed_slider)
        self.robot_mode = int(robot_mode)
        self.safety_mode = int(safety_mode)
        self.remote = bool(remote)
        self.program = program  # a program (not ur-rtde's script) playing on the controller
        self.runtime_state = RUNTIME_PLAYING if program else RUNTIME_STOPPED
        self.script_text = ""
        self.payload: tuple[float, list[float]] | None = None  # what the client set
        self.active_payload = (0.0, [float(c) for c in payload_cog])  # what the arm carries
        self.fieldbus = bool(fieldbus)
        self.reg_int = self.reg_float = 0  # the script's register offsets
        self.noise_m, self.noise_deg = float(noise_m), float(noise_deg)
        self.rng = np.random.default_rng(seed)
        self.T_error = np.eye(4)  # the reported pose's error at the current rest pose
        self.next_move_fault: str | None = None
        self.events: list[str] = []  # faults and stops as they happened
        self.network_fault: str | None = None
        self.in_int: dict[int, int] = {}
        self.in_double: dict[int, float] = {}
        self.out_int = dict.fromkeys(range(24), 0)
        self.out_double = dict.fromkeys(range(24), 0.0)
        self.executing = False
        self.motion: dict | None = None
        self.commands: list[int] = []  # every command id the script processed, in order
        self.texts: list[str] = []  # what the script would textmsg()
        self.script_uploads = 0
        self.dashboard: list[str] = []

    # ------------------------------------------------------------------------------- state
    def tcp_pose(self, reported: bool = False) -> list[float]:
        """The true TCP pose, or as the controller reports it (its kinematic model's error in)."""
        T_error = self.T_error if reported else np.eye(4)
        return ur_pose_from_T(self.T_base_flange @ self.T_flange_tcp @ T_error)

    def _draw_error(self) -> None:
        T = np.eye(4)
        if self.noise_deg > 0:
            T[:3, :3] = R_from_rvec(self.rng.normal(0.0, np.radians(self.noise_deg), 3))
        if self.noise_m > 0:
            T[:3, 3] = self.rng.normal(0.0, self.noise_m, 3)
        self.T_error = T

    def supports(self, cmd: int) -> bool:
        """Whether the uploaded script holds the lines of this command (version-dependent)."""
        fn = SCRIPT_FUNCTION.get(cmd)
        return fn is None or fn in self.script_text

    def fieldbus_has(self, name: str) -> bool:
        """Whether a fieldbus adapter holds this input register (the lower range 0-23)."""
        m = REGISTER.fullmatch(name)
        return self.fieldbus and m is not None and m[1] == "input" and int(m[3]) < 24

    def value(self, name: str) -> object:
        """The current value of an RTDE output variable."""
        if name in CONSTANTS:
            return CONSTANTS[name]
        if name in ATTRIBUTES:
            return getattr(self, ATTRIBUTES[name])
        if name == "timestamp":
            return time.monotonic() - self.t0
        if name in ("actual_q", "target_q"):
            return list(self.q)
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return self.tcp_pose(reported=True)
        if name in ("actual_TCP_speed", "target_TCP_speed"):
            return list(self.speed)
        if name == "safety_status_bits":
            return {2: SAFETY_BIT_NORMAL | SAFETY_BIT_REDUCED, 3: SAFETY_BIT_PROTECTIVE,
                    7: SAFETY_BIT_ROBOT_ESTOP}.get(self.safety_mode, SAFETY_BIT_NORMAL)
        if name == "robot_status_bits":
            running = self.runtime_state == RUNTIME_PLAYING
            return STATUS_BIT_POWER_ON | (STATUS_BIT_PROGRAM_RUNNING if running else 0)
        if REGISTER.fullmatch(name):
            table, i, cast = self._register(name)
            return table.get(i, cast(0))
        if name == "payload":
            return self.active_payload[0]
        if name == "payload_cog":
            return list(self.active_payload[1])
        return {"VECTOR6D": [0.0] * 6, "VECTOR3D": [0.0] * 3, "DOUBLE": 0.0}.get(var_type(name), 0)

    def _register(self, name: str) -> tuple[dict, int, type]:
        """The table, index (the script's offset removed) and type of an RTDE register name."""
        direction, kind, _, number = name.split("_")
        tables = {"input": (self.in_int, self.in_double), "output": (self.out_int, self.out_double)}
        if kind == "int":
            return tables[direction][0], int(number) - self.reg_int, int
        return tables[direction][1], int(number) - self.reg_float, float

    def set_input(self, name: str, val: object) -> None:
        if REGISTER.fullmatch(name) and name.startswith("input_"):
            table, i, cast = self._register(name)
            table[i] = cast(val)

    # ------------------------------------------------------------------------------ script
    def start_script(self, text: str) -> None:
        if self.program:
            self.events.append(f"program {self.program} replaced by an uploaded script")
            self.program = None
        self.script_text = text
        for kind in ("int", "float"):
            # ur-rtde writes the offset after the placeholder's comment, on the next line
            m = re.search(rf"reg_offset_{kind} = \D*?(\d+)", text)
            setattr(self, f"reg_{kind}", int(m.group(1)) if m else 0)
        self.script_uploads += 1
        self.runtime_state = RUNTIME_PLAYING
        self.executing = False
        self.out_int[0] = READY
        self.texts.append("RTDE Control Script Loaded")

    def _script_error(self, text: str) -> None:
        self.texts.append(text)
        self.runtime_state = RUNTIME_STOPPED

    def _doubles(self, first: int, n: int) -> list[float]:
        return [self.in_double.get(first + i, 0.0) for i in range(n)]

    def step(self) -> None:
        """Advance the motion and the control script by one cycle."""
        self._advance_motion()
        if self.runtime_state != RUNTIME_PLAYING:
            return
        if self.program:
            return  # a program that is not ur-rtde's script ignores the registers
        cmd = self.in_int.get(0, 0)
        if cmd == 0:
            self.executing = False
            self.out_int[0] = READY
        elif not self.executing:
            self.executing = True
            self.commands.append(cmd)
            if self._process(cmd) and self.runtime_state == RUNTIME_PLAYING:
                self.out_int[0] = DONE

    def _process(self, cmd: int) -> bool:
        """Run one command; True when it is done now (a blocking move signals done later)."""
        if not self.supports(cmd):
            self.texts.append(f"command {cmd}: no script lines for PolyScope {self.version}")
            return True  # done, the answer registers untouched
        if cmd == MOVEL:
            target = T_from_ur_pose(self._doubles(0, 6)) @ inv_T(self.T_flange_tcp)
            speed, asynchronous = self.in_double.get(6, 0.25), self.in_int.get(1, 0) == 1
            self._start_motion(target, speed, blocking=not asynchronous)
            return asynchronous
        if cmd == STOPL:
            self._stop_motion()
            return True
        if cmd == SET_TCP:
            self.T_flange_tcp = T_from_ur_pose(self._doubles(0, 6))
            return True
        if cmd == GET_TCP_OFFSET:
            for i, v in enumerate(ur_pose_from_T(self.T_flange_tcp)):
                self.out_double[i] = float(v)
            return True
        if cmd == SET_PAYLOAD:
            d = self._doubles(0, 4)
            cog = d[1:4]
            if not any(cog) and "get_target_payload_cog()" in self.script_text:  # $5.0 lines
                cog = list(self.active_payload[1])
            self.payload = self.active_payload = (d[0], cog)
            return True
        if cmd in (IK_ARGS, IK_DEFAULT, IK_HAS_SOLUTION_ARGS, IK_HAS_SOLUTION_DEFAULT):
            near = self._doubles(6, 6) if cmd in (IK_ARGS, IK_HAS_SOLUTION_ARGS) else self.q
            sols = urk.ik(T_from_ur_pose(self._doubles(0, 6)), np.asarray(near), self.model,
                          T_flange_tcp=self.T_flange_tcp)
            if cmd in (IK_HAS_SOLUTION_ARGS, IK_HAS_SOLUTION_DEFAULT):
                self.out_int[1] = 1 if sols else 0
                return True
            if not sols:
                self._script_error("get_inverse_kin: no solution (runtime error, script stopped)")
                return False
            for i, qi in enumerate(sols[0]):
                self.out_double[i] = float(qi)
            return True
        if cmd == IS_POSE_SAFE:
            self.out_int[1] = 1 if self._doubles(0, 6)[2] >= SAFETY_Z_MIN_M else 0
            return True
        if cmd == STOP_SCRIPT:
            self._stop_motion()
            self.runtime_state = RUNTIME_STOPPED
            self.texts.append("Received stop script!")
            return False
        self.texts.append(f"command {cmd} is not simulated: signalled done without effect")
        return True

    # ------------------------------------------------------------------------------ motion
    def _start_motion(self, T_target: np.ndarray, speed_mps: float, blocking: bool) -> None:
        T0 = self.T_base_flange.copy()
        dist = float(np.linalg.norm(T_target[:3, 3] - T0[:3, 3]))
        rvec = np.asarray(rvec_from_R(T0[:3, :3].T @ T_target[:3, :3]))
        slider = max(self.speed_slider, 1e-3)
        duration = max(dist / max(speed_mps, 1e-3), float(np.linalg.norm(rvec)) / 1.0,
                       0.02) / slider
        self.motion = {"T0": T0, "T1": T_target,
                       "t_start": time.monotonic() + MOTION_LATENCY_S,
                       "duration": duration, "blocking": blocking,
                       "fault": self.next_move_fault}
        self.next_move_fault = None
        dt_tcp = (T_target[:3, 3] - T0[:3, 3]) / duration
        self.motion["speed"] = np.concatenate([dt_tcp, T0[:3, :3] @ rvec / duration])

    def _set_flange(self, T: np.ndarray) -> None:
        self.T_base_flange = T
        sols = urk.ik(T, self.q, self.model)
        if sols:
            self.q = sols[0]

    def _advance_motion(self) -> None:
        m = self.motion
        if m is None:
            return
        now = time.monotonic()
        if now < m["t_start"]:
            return  # accepted, not started yet: at rest at the start pose
        self.speed = m["speed"]
        s = min(1.0, (now - m["t_start"]) / m["duration"])
        if m["fault"] and s >= 0.5:
            self._set_flange(interpolate_pose(m["T0"], m["T1"], 0.5))
            fault = m["fault"]
            if fault == "stall":
                m["fault"], m["t_start"], m["duration"] = None, np.inf, 1.0
                self.speed = np.zeros(6)
                self.events.append("stall: the arm stopped halfway through a move")
                return
            self._stop_motion()
            if fault in SAFETY_STOPS:
                self.safety_mode, what = SAFETY_STOPS[fault]
                self.events.append(what)
                self._script_error(f"{what}: the program stopped")
            else:
                self.network_fault = fault  # drop | freeze, acted on by the controller loop
            return
        if m["t_start"] == np.inf:
            return  # stalled: never arrives

        self._set_flange(interpolate_pose(m["T0"], m["T1"], s))
        if s >= 1.0:
            self._stop_motion()
            if m["blocking"] and self.runtime_state == RUNTIME_PLAYING:
                self.out_int[0] = DONE

    def _stop_motion(self) -> None:
        if self.motion is not None:
            self._draw_error()
        self.motion = None
        self.speed = np.zeros(6)

    # --------------------------------------------------------------------------- dashboard
    def dashboard_answer(self, line: str) -> str | None:
        """The dashboard server's answer to one command line (None: close the connection)."""
        self.dashboard.append(line)
        cmd = line.strip()
        running = self.runtime_state == RUNTIME_PLAYING
        if cmd == "quit":
            return None
        major, minor = self.controller_version[:2]
        if cmd in ("is in remote control", "get serial number") and not (
            major >= 5 and minor >= 6
        ):  # PolyScope 5.6+ only
            return f"could not understand: '{cmd}'"
        safety = SAFETY_MODE_NAMES.get(self.safety_mode, "UNDEFINED_SAFETY_MODE")
        name = self.program or ("<unnamed>" if not running else "rtde_control")
        answers = {
            "PolyscopeVersion": self.polyscope_text,
            "get serial number": SERIAL_NUMBER,
            "is in remote control": "true" if self.remote else "false",
            "robotmode": "Robotmode: " + ROBOT_MODE_NAMES.get(self.robot_mode, "NO_CONTROLLER"),
            "safetymode": "Safetymode: " + safety,
            "safetystatus": "Safetystatus: " + safety,
            "running": f"Program running: {'true' if running else 'false'}",
            "programState": ("PLAYING " if running else "STOPPED ") + name,
            "get robot model": self.model.name.rstrip("e"),
            "close popup": "closing popup",
            "close safety popup": "closing safety popup",
        }
        if cmd in answers:
            return answers[cmd]
        if cmd == "stop":
            self._stop_motion()
            if self.program:
                self.events.append(f"program {self.program} stopped from the dashboard")
            self.program = None
            self.runtime_state = RUNTIME_STOPPED
            return "Stopped"
        if cmd == "unlock protective stop":
            if self.safety_mode == 3:
                self.safety_mode = 1
            return "Protective stop releasing"
        return f"could not understand: '{cmd}'"


class Connection:
    """One accepted client socket with its receive buffer."""

    def __init__(self, sock: socket.socket, kind: str) -> None:
        self.sock, self.kind, self.buf = sock, kind, b""
        self.out_names: list[str] = []
        self.frequency = 125.0
        self.inputs: dict[int, list[str]] = {}
        self.started = False
        self.next_send = 0.0
        sock.settimeout(1.0)  # a client that stops reading never blocks the fake for long


class FakeController:
    """Listeners, connections and the event loop."""

    def __init__(self, robot: Robot | None = None, host: str = HOST) -> None:
        self.robot = robot if robot is not None else Robot()
        self.host = host
        self.listeners: dict[socket.socket, str] = {}
        self.conns: list[Connection] = []
        self.blackhole: list[socket.socket] = []
        self.frozen = False
        self.running = True
        self.log: list[str] = []
        #: the longest time between two passes of the event loop (a pass is due every 8 ms at
        #: most): how long this process went unscheduled, e.g. on a host under CPU load
        self.cycle_gap_max_s = 0.0
        self.starve: tuple[float, float] | None = None  # (seconds, every seconds): --starve

    def bind(self) -> None:
        for port, kind in ((RTDE_PORT, "rtde"), (SCRIPT_PORT, "script"),
                           (DASHBOARD_PORT, "dashboard")):
            try:
                s = socket.create_server((self.host, port), backlog=8)  # SO_REUSEADDR on POSIX
            except OSError as e:
                self.close_all()
                raise OSError(f"port {port} ({kind}) on {self.host} is taken: {e}") from None
            self.listeners[s] = kind

    def go_silent(self) -> None:
        """Drop every packet from now on, as a host behind a dead switch does: listeners whose
        accept queue is full and never served, so the kernel drops connection requests (SYN)."""
        for s in self.listeners:
            s.close()
        self.listeners = {}
        for port in (RTDE_PORT, SCRIPT_PORT, DASHBOARD_PORT):
            s = socket.create_server((self.host, port), backlog=0)
            filler = socket.create_connection((self.host, port), timeout=1.0)  # fills the queue
            self.blackhole += [s, filler]

    def close_all(self) -> None:
        for c in self.conns:
            c.sock.close()
        self.conns = []
        for s in [*self.listeners, *self.blackhole]:
            s.close()
        self.listeners = {}
        self.blackhole = []

    def _drop(self, c: Connection) -> None:
        c.sock.close()
        if c in self.conns:
            self.conns.remove(c)

    def _send(self, c: Connection, data: bytes) -> None:
        try:
            c.sock.sendall(data)
        except OSError:
            self._drop(c)

    # ------------------------------------------------------------------------------- RTDE
    def _rtde_message(self, c: Connection, kind: int, payload: bytes) -> None:
        if kind in (S, P):
            c.started, c.next_send = kind == S, time.monotonic()
        if kind in (V, S, P):  # accepted
            self._send(c, message(kind, b"\x01"))
        elif kind == v:
            self._send(c, message(v, struct.pack(">4I", *self.robot.controller_version)))
        elif kind == O:
            c.frequency = struct.unpack(">d", payload[:8])[0]
            c.out_names = [n for n in payload[8:].decode().split(",") if n]
            types = [var_type(n) for n in c.out_names]
            self.log.append(f"output recipe at {c.frequency:g} Hz: {','.join(c.out_names)}")
            self._send(c, message(O, b"\x01" + ",".join(types).encode()))
        elif kind == I:
            names = [n for n in payload.decode().split(",") if n]
            rid = len(c.inputs) + 1
            c.inputs[rid] = names
            types = ["IN_USE" if self.robot.fieldbus_has(n) else var_type(n) for n in names]
            self._send(c, message(I, bytes([rid]) + ",".join(types).encode()))
        elif kind == U:
            self._data_package(c, payload)

    def _data_package(self, c: Connection, payload: bytes) -> None:
        names = c.inputs.get(payload[0], [])
        off = 1
        for n in names:
            fmt = FORMATS.get(var_type(n))
            if fmt is None or off + struct.calcsize(fmt) > len(payload):
                break  # the client packs only the fields a command needs
            vals = struct.unpack_from(fmt, payload, off)
            off += struct.calcsize(fmt)
            self.robot.set_input(n, vals[0] if len(vals) == 1 else vals)

    def _state_package(self, c: Connection) -> bytes:
        parts = [b"\x01"]
        for n in c.out_names:
            val = self.robot.value(n)
            fmt = FORMATS[var_type(n)]
            parts.append(struct.pack(fmt, *val) if isinstance(val, list) else
                         struct.pack(fmt, val))
        return message(U, b"".join(parts))

    # ---------------------------------------------------------------------- other sockets
    def _on_data(self, c: Connection, data: bytes) -> None:
        c.buf += data
        if c.kind == "rtde":
            while len(c.buf) >= 3:
                size, kind = struct.unpack(">HB", c.buf[:3])
                if len(c.buf) < size:
                    break
                payload, c.buf = c.buf[3:size], c.buf[size:]
                self._rtde_message(c, kind, payload)
        elif c.kind == "dashboard":
            while b"\n" in c.buf:
                line, c.buf = c.buf.split(b"\n", 1)
                answer = self.robot.dashboard_answer(line.decode(errors="replace"))
                if answer is None:
                    self._send(c, b"Disconnected\n")
                    self._drop(c)
                    return
                self._send(c, answer.encode() + b"\n")
        else:  # script port: run a program once its top-level "end" line is in
            text = c.buf.decode(errors="replace")
            lines = text.split("\n")
            if any(ln.startswith("def ") for ln in lines) and any(
                ln.rstrip() == "end" for ln in lines[:-1]
            ):
                self.log.append(f"script received: {len(c.buf)} bytes")
                self.robot.start_script(text)
                c.buf = b""

    def _control(self, line: str) -> None:
        cmd = line.strip()
        r = self.robot
        word, _, arg = cmd.partition(" ")
        if cmd == "state":
            print(json.dumps({
                "tcp_pose": r.tcp_pose(), "flange_pose": ur_pose_from_T(r.T_base_flange),
                "reported_tcp_pose": r.tcp_pose(reported=True),
                "tcp": ur_pose_from_T(r.T_flange_tcp), "q": list(r.q),
                "safety_mode": r.safety_mode, "robot_mode": r.robot_mode,
                "runtime_state": r.runtime_state, "program": r.program,
                "speed_slider": r.speed_slider, "version": r.version,
                "payload": None if r.payload is None else [r.payload[0], r.payload[1]],
                "moving": r.motion is not None and r.motion["t_start"] != np.inf,
                "stalled": r.motion is not None and r.motion["t_start"] == np.inf,
                "commands": r.commands, "texts": r.texts, "events": r.events,
                "script_uploads": r.script_uploads, "dashboard": r.dashboard, "log": self.log,
                "connections": [c.kind for c in self.conns], "frozen": self.frozen,
                "cycle_gap_max_s": self.cycle_gap_max_s,
            }), flush=True)
            return
        if cmd in ("pstop", "estop", "stall", "drop_next", "freeze_next"):
            r.next_move_fault = cmd.removesuffix("_next")
        elif cmd == "freeze":
            self.frozen = True
            self.go_silent()
        elif cmd == "drop":
            self.close_all()
        elif cmd == "reopen":
            self.bind()
        elif word in SETTINGS and arg:
            setattr(r, SETTINGS[word][0], SETTINGS[word][1](arg))
        elif word == "program" and arg:
            r.program, r.runtime_state = arg, RUNTIME_PLAYING
        elif cmd in ("quit", ""):
            self.running = False
        else:
            print(json.dumps({"error": f"unknown control command {cmd!r}"}), flush=True)
            return
        print(json.dumps({"ok": cmd}), flush=True)

    # --------------------------------------------------------------------------------- loop
    def run(self) -> None:
        stdin = sys.stdin.fileno()
        last = time.monotonic()
        next_starve = last + (self.starve[1] if self.starve else 0.0)
        while self.running:
            if self.starve is not None and time.monotonic() >= next_starve:
                time.sleep(self.starve[0])  # a host that does not schedule this process
                next_starve = time.monotonic() + self.starve[1]
            now = time.monotonic()
            self.cycle_gap_max_s, last = max(self.cycle_gap_max_s, now - last), now
            started = [c for c in self.conns if c.started and not self.frozen]
            timeout = min([max(0.0, c.next_send - now) for c in started], default=0.008)
            readers = [stdin, *self.listeners, *(c.sock for c in self.conns)]
            ready, _, _ = select.select(readers, [], [], min(timeout, 0.008))
            for fd in ready:
                if fd == stdin:
                    line = os.read(stdin, 4096).decode()
                    for ln in (line.splitlines() or [""]):
                        self._control(ln)
                elif fd in self.listeners:
                    sock, _ = fd.accept()
                    conn = Connection(sock, self.listeners[fd])
                    self.conns.append(conn)
                    if conn.kind == "dashboard":
                        self._send(conn, b"Connected: Universal Robots Dashboard Server\n")
                else:
                    c = next((c for c in self.conns if c.sock is fd), None)
                    if c is None:
                        continue
                    try:
                        data = fd.recv(65536)
                    except OSError:
                        data = b""
                    if not data:
                        self._drop(c)
                    elif not self.frozen:  # frozen: read and ignore, answer nothing
                        self._on_data(c, data)
            self.robot.step()
            fault, self.robot.network_fault = self.robot.network_fault, None
            if fault == "drop":
                self.robot.events.append("connection dropped")
                self.close_all()
            elif fault == "freeze":
                self.robot.events.append("network went silent")
                self.frozen = True
                self.go_silent()
            if self.frozen:
                continue
            now = time.monotonic()
            for c in list(self.conns):
                if c.started and now >= c.next_send:
                    c.next_send = max(c.next_send + 1.0 / c.frequency, now)
                    self._send(c, self._state_package(c))
        self.close_all()


def _floats(text: str) -> list[float]:
    return [float(v) for v in text.replace(",", " ").split()]


def build_parser() -> argparse.ArgumentParser:
    """The controller's command line (docs/DRIVERS.md)."""
    p = argparse.ArgumentParser(
        prog="python -m slidecal.mocks.ur_controller",
        description="A loopback UR controller for the real ur-rtde client.",
    )
    p.add_argument("--host", default=HOST, help="loopback address to bind (127.x.y.z)")
    p.add_argument("--polyscope", default=DEFAULT_VERSION, choices=list(VERSIONS))
    p.add_argument("--model", default="UR5e", help="UR5e, UR10e, ... (the kinematics)")
    p.add_argument("--start-q", type=_floats, help="six start joint angles, radians")
    p.add_argument("--speed-slider", type=float, default=1.0, help="pendant speed slider, 0-1")
    p.add_argument("--robot-mode", type=int, default=7)
    p.add_argument("--safety-mode", type=int, default=1)
    p.add_argument("--local", action="store_true", help="in local control (e-Series)")
    p.add_argument("--program", help="a program already playing on the controller")
    p.add_argument("--noise-mm", type=float, default=0.0, help="reported position error")
    p.add_argument("--noise-deg", type=float, default=0.0, help="reported rotation error")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--payload-cog", type=_floats, default=[0.0, 0.0, 0.0],
                   help="the payload's centre of gravity set on the pendant, metres")
    p.add_argument("--starve", type=_floats, metavar="S,EVERY_S",
                   help="stall the event loop S seconds every EVERY_S seconds (host CPU load)")
    p.add_argument("--fieldbus", action="store_true",
                   help="EtherNet/IP, PROFINET or MODBUS holds input registers 0-23")
    p.add_argument("--silent", action="store_true", help="drop every packet (a dead host)")
    return p


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    try:
        robot = Robot(a.polyscope, a.model, Q0 if a.start_q is None else np.array(a.start_q),
                      a.speed_slider, a.robot_mode, a.safety_mode, not a.local, a.program,
                      a.noise_mm / 1000.0, a.noise_deg, a.seed, a.payload_cog, a.fieldbus)
    except Exception as e:  # noqa: BLE001 - reported on the channel the parent reads
        print(json.dumps({"error": f"bad option: {e}"}), flush=True)
        return 2
    fake = FakeController(robot, a.host)
    fake.starve = None if a.starve is None else (a.starve[0], a.starve[1])
    try:
        fake.bind()
        if a.silent:
            fake.go_silent()
    except OSError as e:
        print(json.dumps({"error": str(e)}), flush=True)
        return 2
    print(json.dumps({"ready": True, "pid": os.getpid(), "host": a.host,
                      "ports": [RTDE_PORT, SCRIPT_PORT, DASHBOARD_PORT]}), flush=True)
    fake.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())

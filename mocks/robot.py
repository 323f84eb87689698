"""A simulated UR e-Series arm (``Robot`` protocol of ``drivers/base.py``) and a real arm's
kinematic error: docs/DRIVERS.md (the model, ``measured_pose`` against ``true_pose``, the cell)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from slidecal.drivers import ur_kinematics as urk
from slidecal.drivers.base import checked_move
from slidecal.drivers.ur_kinematics import trapezoid_time_s
from slidecal.drivers.ur_pose import T_from_ur_pose, describe
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, rvec_from_R

#: Straight lines are checked at least every 5 mm and every 1 deg of tool rotation.
STEP_M = 0.005
STEP_RAD = np.radians(1.0)
#: Largest joint change between two such samples before the path is discontinuous (a branch flip).
MAX_JOINT_STEP_RAD = 0.2

#: The move limits that must be positive (``SimulatedUR``'s arguments, the cell's ``limits:``).
SPEED_LIMITS = (
    "max_speed_mps",
    "max_accel_mps2",
    "max_angular_speed_deg_s",
    "max_angular_accel_deg_s2",
)
FAULT_KINDS = ("protective_stop", "emergency_stop", "disconnect", "timeout")
#: The stops a fault leaves the arm in: what the controller calls it and what the operator does.
STOPS = {
    "protective_stop": (
        "protective stop", "check the cell for a collision, unlock it on the pendant and restart"
    ),
    "emergency_stop": (
        "robot emergency stop", "release the emergency-stop button and reset it on the pendant"
    ),
}
#: Cycles per joint turn of the simulated gearboxes' transmission error (a 12 deg period).
GEAR_CYCLES = 30.0


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose a fraction ``s`` along the straight line (and rotation geodesic) from T0 to T1."""
    rvec = rvec_from_R(T0[:3, :3].T @ T1[:3, :3])
    return T_from_Rt(T0[:3, :3] @ R_from_rvec(s * rvec), (1 - s) * T0[:3, 3] + s * T1[:3, 3])


@dataclass(frozen=True)
class KinematicError:
    """How a real arm differs from its nominal Denavit-Hartenberg model (all (6,) per joint).

    Joint ``i`` of the true arm is ``Rz(q_i + d_theta_i + e_i(q)) Tz(d_i + d_d_i) Tx(a_i + d_a_i)
    Rx(alpha_i + d_alpha_i)`` with ``e_i(q) = gravity_rad_i cos(load angle) + cyclic_rad_i sin(2 q_i
    + cyclic_phase_i) + gear_rad_i sin(GEAR_CYCLES q_i + gear_phase_i)`` (load angle ``q2`` for
    joint 2, ``q2 + q3`` for joint 3, no gravity term elsewhere). ``repeatability_m``,
    ``repeatability_deg``: one-sigma per axis of each stop's random error.
    """

    d_theta: np.ndarray
    d_d: np.ndarray
    d_a: np.ndarray
    d_alpha: np.ndarray
    gravity_rad: np.ndarray
    cyclic_rad: np.ndarray
    cyclic_phase: np.ndarray
    gear_rad: np.ndarray
    gear_phase: np.ndarray
    repeatability_m: float = 3e-5
    repeatability_deg: float = 0.005

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        mm: float = 1.0,
        deg: float = 0.1,
        repeatability_mm: float = 0.03,
        repeatability_deg: float = 0.005,
    ) -> KinematicError:
        """A random arm whose flange errs by about ``mm`` and ``deg`` (rms over the workspace):
        angular parameters drawn at ``deg / 3`` one-sigma each, lengths at ``mm / 3``."""
        if mm < 0 or deg < 0 or repeatability_mm < 0 or repeatability_deg < 0:
            raise InputError("kinematic_error sizes must not be negative", where="robot")
        ang = np.radians(deg) / 3.0
        lin = mm / 1000.0 / 3.0
        twist = rng.normal(0.0, ang, 6)
        twist[[0, 3, 4, 5]] *= 0.5  # the perpendicular axes are machined more easily than the
        # nominally parallel shoulder/elbow/wrist-1 axes, whose misalignment builds up
        return cls(
            d_theta=rng.normal(0.0, ang, 6),
            d_d=rng.normal(0.0, lin, 6),
            d_a=rng.normal(0.0, lin, 6) * np.array([0, 1, 1, 0, 0, 0]),
            d_alpha=twist,
            gravity_rad=np.abs(rng.normal(0.0, ang, 6)) * np.array([0, 1, 1, 0, 0, 0]),
            cyclic_rad=rng.normal(0.0, 0.3 * ang, 6),
            cyclic_phase=rng.uniform(0.0, 2 * np.pi, 6),
            gear_rad=rng.normal(0.0, 0.5 * ang, 6),
            gear_phase=rng.uniform(0.0, 2 * np.pi, 6),
            repeatability_m=repeatability_mm / 1000.0,
            repeatability_deg=repeatability_deg,
        )

    def joint_errors(self, q: np.ndarray) -> np.ndarray:
        """The joint-angle errors (6,) radians at joints ``q`` (offsets, sag, transmission)."""
        load = np.array([0.0, q[1], q[1] + q[2], 0.0, 0.0, 0.0])
        return (
            self.d_theta
            + self.gravity_rad * np.cos(load)
            + self.cyclic_rad * np.sin(2.0 * q + self.cyclic_phase)
            + self.gear_rad * np.sin(GEAR_CYCLES * q + self.gear_phase)
        )

    def stop_error(self, rng: np.random.Generator) -> np.ndarray:
        """One stop's random repeatability error (4, 4): the true pose is ``fk(q) @`` it."""
        dR = R_from_rvec(rng.normal(0.0, np.radians(self.repeatability_deg), 3))
        return T_from_Rt(dR, rng.normal(0.0, self.repeatability_m, 3))

    def fk(
        self, q: np.ndarray, model: urk.URModel, T_flange_tcp: np.ndarray | None = None
    ) -> np.ndarray:
        """The true ``T_base_tool`` (4, 4) of the arm at joints ``q`` (without repeatability)."""
        q = np.asarray(q, dtype=float)
        dh_error = (self.d_d, self.d_a, self.d_alpha)
        return urk.fk(q + self.joint_errors(q), model, T_flange_tcp, dh_error)


class SimulatedUR:
    """A simulated UR arm (docs/DRIVERS.md).

    ``rng``: draws the measurement noise. ``model``: ``ur_kinematics.UR5E`` ... ``start_q`` (6,)
    rad. ``T_flange_tcp`` (4, 4) m (None: the flange). ``max_speed_mps``, ``max_accel_mps2``,
    ``max_angular_speed_deg_s``, ``max_angular_accel_deg_s2``: the move's limits. ``pose_noise_m``,
    ``pose_noise_deg``: one-sigma of the measured position per axis and of each rotation-vector
    component. ``z_min_m``: lowest TCP height (None: none). ``move_timeout_s``: what a timed-out
    move spends. ``kinematic_error``: the arm's deviation from its model (None: exact);
    ``true_pose`` is then the perturbed arm's, ``measured_pose`` the nominal model's.
    """

    def __init__(
        self,
        rng: np.random.Generator,
        *,
        model: urk.URModel = urk.UR5E,
        start_q: np.ndarray = urk.Q_HOME,
        T_flange_tcp: np.ndarray | None = None,
        max_speed_mps: float = 1.0,
        max_accel_mps2: float = 2.5,
        max_angular_speed_deg_s: float = 60.0,
        max_angular_accel_deg_s2: float = 80.0,
        pose_noise_m: float = 0.0,
        pose_noise_deg: float = 0.0,
        z_min_m: float | None = None,
        move_timeout_s: float = 30.0,
        kinematic_error: KinematicError | None = None,
    ) -> None:
        speeds = (max_speed_mps, max_accel_mps2, max_angular_speed_deg_s, max_angular_accel_deg_s2)
        for name, value in zip(SPEED_LIMITS, speeds, strict=True):
            if not value > 0:
                raise InputError(f"{name} must be positive, got {value}")
        if pose_noise_m < 0 or pose_noise_deg < 0:
            raise InputError("pose_noise_m and pose_noise_deg must not be negative")
        self.rng = rng
        self.model = model
        self.T_flange_tcp = None if T_flange_tcp is None else np.asarray(T_flange_tcp, float)
        self.max_speed_mps = float(max_speed_mps)
        self.max_accel_mps2 = float(max_accel_mps2)
        self.max_angular_speed_rad_s = float(np.radians(max_angular_speed_deg_s))
        self.max_angular_accel_rad_s2 = float(np.radians(max_angular_accel_deg_s2))
        self.pose_noise_m = float(pose_noise_m)
        self.pose_noise_deg = float(pose_noise_deg)
        self.z_min_m = z_min_m
        self.move_timeout_s = float(move_timeout_s)
        self._q = np.asarray(start_q, dtype=float).reshape(6).copy()
        if urk.singularity(self._q, model) is not None:
            raise InputError(f"start joints are singular: {urk.singularity(self._q, model)}")
        self._T = urk.fk(self._q, model, self.T_flange_tcp)
        self.kinematic_error = kinematic_error
        self._stop_error = np.eye(4)  # this stop's repeatability error (true = fk_true @ it)
        self.robot_time_s = 0.0  # simulated time spent moving and settling
        self._connected = False
        self.moves = 0  # move_linear calls made, refused ones included
        self._faults: dict[int, str] = {}
        self._state_fault: str | None = None
        self.stop_calls = 0
        self.move_log: list[np.ndarray] = []

    # ----------------------------------------------------------------- construction from YAML
    @classmethod
    def from_dict(cls, cell: Mapping[str, Any]) -> SimulatedUR:
        """Build from a cell description (docs/DRIVERS.md); unknown keys are errors."""
        known = {
            "model",
            "start_pose",
            "start_q",
            "tcp",
            "limits",
            "noise",
            "seed",
            "kinematic_error",
        }
        unknown = set(cell) - known
        if unknown:
            raise InputError(
                f"unknown key(s) {sorted(unknown)}; the robot section takes {sorted(known)}",
                where="robot",
            )
        model = urk.model_by_name(str(cell.get("model", "UR5e")))
        T_flange_tcp = T_from_ur_pose(cell["tcp"]) if cell.get("tcp") is not None else None
        limits = dict(cell.get("limits") or {})
        noise = dict(cell.get("noise") or {})
        limit_keys = (*SPEED_LIMITS, "z_min_m", "move_timeout_s")
        kw: dict[str, Any] = {k: limits.pop(k) for k in limit_keys if k in limits}
        kw |= {k: float(noise.pop(k)) for k in ("pose_noise_m", "pose_noise_deg") if k in noise}
        if limits or noise:
            raise InputError(f"unknown key(s) {sorted(limits) + sorted(noise)}", where="robot")
        if cell.get("start_q") is not None:
            start_q = np.asarray(cell["start_q"], dtype=float)
        elif cell.get("start_pose") is not None:
            try:
                T_start = T_from_ur_pose(cell["start_pose"])
            except ValueError as e:
                raise InputError(str(e), where="robot.start_pose") from None
            sols = [
                q
                for q in urk.ik(T_start, urk.Q_HOME, model, T_flange_tcp)
                if urk.singularity(q, model) is None
            ]
            if not sols:
                raise InputError(
                    f"start pose {describe(T_start)} is out of reach or singular for a "
                    f"{model.name}; move it closer to the base or give start_q",
                    where="robot.start_pose",
                )
            start_q = sols[0]
        else:
            start_q = urk.Q_HOME
        rng = np.random.default_rng(cell.get("seed", 0))
        ke = cell.get("kinematic_error")
        if ke is not None:
            ke = dict(ke)
            size_keys = ("mm", "deg", "repeatability_mm", "repeatability_deg")
            sizes = {k: float(ke.pop(k)) for k in size_keys if k in ke}
            if ke:
                raise InputError(
                    f"unknown key(s) {sorted(ke)}; kinematic_error takes mm, deg, "
                    "repeatability_mm, repeatability_deg",
                    where="robot.kinematic_error",
                )
            kw["kinematic_error"] = KinematicError.random(rng, **sizes)
        return cls(rng, model=model, start_q=start_q, T_flange_tcp=T_flange_tcp, **kw)

    # ----------------------------------------------------------------------- simulation only
    def true_pose(self) -> np.ndarray:
        """The true ``T_base_tool`` (4, 4), metres (for the simulated cameras; not in Robot):
        the nominal pose, or with a ``kinematic_error`` the real arm's pose of the joints."""
        if self.kinematic_error is None:
            return self._T.copy()
        return self.kinematic_error.fk(self._q, self.model, self.T_flange_tcp) @ self._stop_error

    def _new_stop(self) -> None:
        """Draw the repeatability error of the stop just reached."""
        ke = self.kinematic_error
        if ke is not None and (ke.repeatability_m != 0 or ke.repeatability_deg != 0):
            self._stop_error = ke.stop_error(self.rng)

    @property
    def q(self) -> np.ndarray:
        """The current joint vector (6,), radians."""
        return self._q.copy()

    def inject_fault(self, kind: str, at_move: int) -> None:
        """Make ``move_linear`` call number ``at_move`` (from 0) fail: ``"protective_stop"`` /
        ``"emergency_stop"`` stop halfway and raise until :meth:`clear_fault`; ``"disconnect"``
        arrives, then every call raises (stale data); ``"timeout"`` stalls halfway and raises after
        ``move_timeout_s``."""
        if kind not in FAULT_KINDS:
            raise InputError(f"unknown fault kind {kind!r}; use one of {FAULT_KINDS}")
        self._faults[int(at_move)] = kind

    def clear_fault(self) -> None:
        """What an operator does after a fault: unlock the protective stop, reconnect."""
        self._state_fault = None

    # ------------------------------------------------------------------------ Robot protocol
    def connect(self) -> None:
        """Open the (simulated) connection."""
        if self._state_fault is not None:
            raise HardwareFault(f"cannot connect: {self._state_fault}")
        self._connected = True

    def close(self) -> None:
        """Close the connection (idempotent); never moves the robot."""
        self._connected = False

    def _check_ready(self) -> None:
        if self._state_fault is not None:
            raise HardwareFault(self._state_fault)
        if not self._connected:
            raise HardwareFault("robot not connected: call connect() first")

    def measured_pose(self) -> np.ndarray:
        """``T_base_tool`` (4, 4), metres, with the configured measurement noise."""
        self._check_ready()
        T = self._T.copy()
        if self.pose_noise_m > 0:
            T[:3, 3] += self.rng.normal(0.0, self.pose_noise_m, 3)
        if self.pose_noise_deg > 0:
            dR = R_from_rvec(self.rng.normal(0.0, np.radians(self.pose_noise_deg), 3))
            T[:3, :3] = T[:3, :3] @ dR
        return T

    def _check_line(self, T0: np.ndarray, T1: np.ndarray, n: int) -> list[np.ndarray]:
        """Joint vectors at ``n`` steps along the line T0 -> T1; raise ``HardwareFault`` naming a
        bad pose."""
        q_prev = self._q
        qs = []
        for k in range(1, n + 1):
            T = interpolate_pose(T0, T1, k / n)
            where = f"pose {describe(T)} ({k}/{n} along the move to {describe(T1)})"
            if self.z_min_m is not None and T[2, 3] < self.z_min_m:
                raise HardwareFault(
                    f"{where} is below the safety plane z = {self.z_min_m} m; plan higher poses"
                )
            sols = urk.ik(T, q_prev, self.model, self.T_flange_tcp)
            if not sols:
                raise HardwareFault(
                    f"{where} is out of reach or outside the joint limits; plan poses closer "
                    "to the robot's usual workspace"
                )
            q = sols[0]
            sing = urk.singularity(q, self.model)
            if sing is not None:
                raise HardwareFault(f"{where} passes near a {sing}; plan around it")
            jump = float(np.max(np.abs(q - q_prev)))
            if jump > MAX_JOINT_STEP_RAD:
                raise HardwareFault(
                    f"{where} needs a joint jump of {np.degrees(jump):.1f} deg (a configuration "
                    "change); a linear move cannot do that, plan a shorter or different move"
                )
            qs.append(q)
            q_prev = q
        return qs

    def move_linear(self, T_base_tool: np.ndarray, speed_mps: float, accel_mps2: float) -> None:
        """Move the TCP in a straight line to ``T_base_tool`` (4, 4), metres; block until there.
        ``HardwareFault`` when the line leaves the workspace or a fault occurs."""
        move_index = self.moves
        self.moves += 1
        self._check_ready()
        T1 = checked_move(self, T_base_tool, speed_mps, accel_mps2)
        T0 = self._T
        length = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        angle = float(np.linalg.norm(rvec_from_R(T0[:3, :3].T @ T1[:3, :3])))
        n = max(1, int(np.ceil(length / STEP_M)), int(np.ceil(angle / STEP_RAD)))
        qs = self._check_line(T0, T1, n)
        duration = max(
            trapezoid_time_s(length, speed_mps, accel_mps2),
            trapezoid_time_s(angle, self.max_angular_speed_rad_s, self.max_angular_accel_rad_s2),
        )
        fault = self._faults.pop(move_index, None)
        if fault in ("protective_stop", "emergency_stop", "timeout"):
            half = len(qs) // 2
            if half > 0:
                self._q = qs[half - 1]
                self._T = urk.fk(self._q, self.model, self.T_flange_tcp)
            if fault in STOPS:
                self.robot_time_s += duration / 2
                what, fix = STOPS[fault]
                self._state_fault = f"{what} during move {move_index} at {describe(self._T)}; {fix}"
                raise HardwareFault(self._state_fault)
            self.robot_time_s += self.move_timeout_s
            raise HardwareFault(
                f"move {move_index} to {describe(T1)} did not finish within "
                f"{self.move_timeout_s} s; check that the robot is in remote control and running"
            )
        self._q = qs[-1]
        self._T = urk.fk(self._q, self.model, self.T_flange_tcp)
        self._new_stop()
        self.robot_time_s += duration
        self.move_log.append(self._T.copy())
        if fault == "disconnect":
            self._state_fault = (
                "connection to the robot lost (the pose data stopped updating); check the "
                "network cable and the controller, then reconnect"
            )

    def wait_settled(self, settle_s: float) -> None:
        """Add ``settle_s`` seconds to the clock (the simulated arm has no vibration)."""
        if settle_s < 0:
            raise InputError(f"settle_s must not be negative, got {settle_s}")
        self._check_ready()
        self.robot_time_s += float(settle_s)

    def stop(self) -> None:
        """Record the stop (the simulated arm is never moving between calls)."""
        self.stop_calls += 1

    @property
    def stopped(self) -> bool:
        """Whether :meth:`stop` was ever called."""
        return self.stop_calls > 0

    def is_reachable(self, T_base_tool: np.ndarray) -> bool:
        """Whether the pose has a non-singular solution near the current joints, inside limits."""
        T = np.asarray(T_base_tool, dtype=float)
        if self.z_min_m is not None and T[2, 3] < self.z_min_m:
            return False
        return urk.reachable(T, self._q, self.model, self.T_flange_tcp)

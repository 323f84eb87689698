"""URRobot against fakes of the ur-rtde modules (rtde_control, rtde_receive, dashboard_client).

The fakes copy the real method names and signatures of ur-rtde 1.6.5 (a test checks them
against the installed modules) and the semantics of the library's sources
(``rtde_control_interface.cpp``, ``dashboard_client.cpp``): moveL returns False on a protective
stop, the receive interface keeps returning its last values after a lost connection while
isConnected() turns False and getTimestamp() stops advancing, getInverseKinematics returns []
and isPoseWithinSafetyLimits False when the command fails (e.g. the control script stopped),
getTCPOffset raises RuntimeError then, the dashboard's ``running`` is False for a paused program.
"""

from __future__ import annotations

import sys
import types
from pathlib import Path

import numpy as np
import pytest

from slidecal.drivers import ur_kinematics as urk
from slidecal.drivers.base import Robot
from slidecal.drivers.ur import URRobot
from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.solver.errors import HardwareFault, InputError
from slidecal.solver.geometry import T_from_Rt

Q0 = np.array([0.0, -1.9, 1.7, -1.37, -1.57, 0.0])


class FakeController:
    """The state of a fake UR controller shared by the three fake clients."""

    def __init__(self) -> None:
        self.q = Q0.copy()
        self.pose = ur_pose_from_T(urk.fk(Q0))
        self.timestamp = 100.0
        self.frozen = False
        self.connected = True
        self.robot_mode = 7
        self.safety_mode = 1
        self.remote = True
        self.tcp = [0.0] * 6
        self.next_move = "ok"  # ok | protective_stop | estop | no_motion | raise
        self.calls: list[tuple] = []
        self.unreachable = False
        self.outside_safety = False
        self.refuse_connection = False
        self.version = "5.12.2.1101534"
        self.program: str | None = None
        self.speed_scaling = 1.0  # the trajectory limiter's factor
        self.target_speed_fraction = 1.0  # the pendant's slider
        self.payload: tuple | None = None
        self.paused: str | None = None  # a program paused on the pendant
        self.runtime_state: int | None = None  # None: from program / paused
        self.script_running = True  # ur-rtde's control script, once uploaded
        self.tcp_offset_fails = False

    def runtime(self) -> int:
        if self.runtime_state is not None:
            return self.runtime_state
        return 2 if self.program else 4 if self.paused else 1


#: module name -> the fake class installed for it (filled by install_fakes)
FAKES: dict[str, type] = {}


def install_fakes(monkeypatch: pytest.MonkeyPatch, ctl: FakeController) -> None:
    class RTDEReceiveInterface:
        def __init__(self, hostname, frequency=-1.0, variables=(), verbose=False,
                     use_upper_range_registers=False, rt_priority=0):
            if ctl.refuse_connection:
                raise RuntimeError("Connection refused")
            ctl.calls.append(("RTDEReceiveInterface", hostname, frequency))

        def isConnected(self):
            return ctl.connected

        def getTimestamp(self):
            if ctl.connected and not ctl.frozen:
                ctl.timestamp += 0.002
            return ctl.timestamp

        def getActualTCPPose(self):
            return list(ctl.pose)  # the last values, also after a lost connection

        def getActualQ(self):
            return list(ctl.q)

        def getActualTCPSpeed(self):
            return [0.0] * 6

        def getSpeedScaling(self):
            return ctl.speed_scaling

        def getTargetSpeedFraction(self):
            return ctl.target_speed_fraction

        def getSpeedScalingCombined(self):  # computed by the client (rtde_receive_interface.cpp)
            return ctl.speed_scaling * ctl.target_speed_fraction

        def getRobotMode(self):
            return ctl.robot_mode

        def getSafetyMode(self):
            return ctl.safety_mode

        def getRuntimeState(self):
            return ctl.runtime()

        def isProtectiveStopped(self):
            return ctl.safety_mode == 3

        def isEmergencyStopped(self):
            return ctl.safety_mode in (6, 7)

        def disconnect(self):
            ctl.calls.append(("receive.disconnect",))

    class RTDEControlInterface:
        #: the members of ur-rtde's Flags enum the driver uses (checked against ur-rtde below)
        Flags = types.SimpleNamespace(FLAG_UPLOAD_SCRIPT=1, FLAG_UPPER_RANGE_REGISTERS=8)

        def __init__(self, hostname, frequency=-1.0, flags=1, ur_cap_port=50002, rt_priority=0):
            ctl.calls.append(("RTDEControlInterface", hostname, frequency))

        def isConnected(self):
            return ctl.connected

        def moveL(self, pose, speed=0.25, acceleration=1.2, asynchronous=False):
            if not 0 <= speed <= 3 or not 0 <= acceleration <= 150:
                raise ValueError("speed or acceleration out of range")
            ctl.calls.append(("moveL", list(pose), speed, acceleration, asynchronous))
            kind, ctl.next_move = ctl.next_move, "ok"
            if kind == "protective_stop":
                ctl.safety_mode = 3
                return False
            if kind == "estop":
                ctl.safety_mode = 7
                return False
            if kind == "raise":
                raise RuntimeError("RTDE control script is not running!")
            if kind == "disconnect":
                ctl.connected = False
                return False
            if kind == "ok":
                ctl.pose = list(pose)
            return True

        def stopL(self, a=10.0, asynchronous=False):
            ctl.calls.append(("stopL", a))

        def getTCPOffset(self):
            if ctl.tcp_offset_fails:
                raise RuntimeError("getTCPOffset() function did not succeed!")
            return list(ctl.tcp)

        def isProgramRunning(self):
            return ctl.script_running

        def setPayload(self, mass, cog):
            ctl.calls.append(("setPayload", mass, list(cog)))
            ctl.payload = (mass, list(cog))
            return True

        def setTcp(self, tcp_offset):
            ctl.calls.append(("setTcp", list(tcp_offset)))
            ctl.tcp = list(tcp_offset)
            return True

        def getInverseKinematics(self, x, qnear=(), max_position_error=1e-10,
                                 max_orientation_error=1e-10):
            ctl.calls.append(("getInverseKinematics", list(x), list(qnear)))
            if ctl.unreachable:
                return []
            sols = urk.ik(T_from_ur_pose(x), np.asarray(qnear))
            return list(sols[0]) if sols else []

        def getInverseKinematicsHasSolution(self, x, qnear=(), max_position_error=1e-10,
                                            max_orientation_error=1e-10):
            ctl.calls.append(("getInverseKinematicsHasSolution", list(x), list(qnear)))
            return not ctl.unreachable and bool(urk.ik(T_from_ur_pose(x), np.asarray(qnear)))

        def isPoseWithinSafetyLimits(self, pose):
            return ctl.script_running and not ctl.outside_safety

        def stopScript(self):
            ctl.calls.append(("stopScript",))

        def disconnect(self):
            ctl.calls.append(("control.disconnect",))

    class DashboardClient:
        def __init__(self, hostname, port=29999, verbose=False):
            pass

        def connect(self, timeout_ms=2000):
            ctl.calls.append(("dashboard.connect",))

        def isConnected(self):
            return True

        def polyscopeVersion(self):
            return ctl.version

        def getRobotModel(self):
            return "UR5"

        def getSerialNumber(self):
            if int(ctl.version.split(".")[0]) == 5 and int(ctl.version.split(".")[1]) > 5:
                return "20185500001"
            raise RuntimeError("getSerialNumber() function is not supported")

        def running(self):  # the dashboard answers "Program running: false" when paused
            return ctl.program is not None

        def programState(self):
            if ctl.program:
                return f"PLAYING {ctl.program}"
            return f"PAUSED {ctl.paused}" if ctl.paused else "STOPPED <unnamed>"

        def isInRemoteControl(self):
            if ctl.remote is None:  # the socket failed: ur-rtde lets boost's error through
                raise RuntimeError("read: End of file [asio.misc:2]")
            return ctl.remote

        def unlockProtectiveStop(self):
            ctl.calls.append(("unlockProtectiveStop",))

        def disconnect(self):
            pass

    FAKES.update(rtde_receive=RTDEReceiveInterface, rtde_control=RTDEControlInterface,
                 dashboard_client=DashboardClient)
    import slidecal.drivers.ur as ur_module

    monkeypatch.setattr(ur_module, "probe_controller", lambda host, timeout_s: (5, 12, 2, 0))
    for name, cls in (
        ("rtde_receive", RTDEReceiveInterface),
        ("rtde_control", RTDEControlInterface),
        ("dashboard_client", DashboardClient),
    ):
        mod = types.ModuleType(name)
        setattr(mod, cls.__name__, cls)
        monkeypatch.setitem(sys.modules, name, mod)


@pytest.fixture
def ctl(monkeypatch):
    c = FakeController()
    install_fakes(monkeypatch, c)
    return c


def _names(ctl):
    return [c[0] for c in ctl.calls]


def test_connect_and_measured_pose(ctl):
    tcp = T_from_Rt(np.eye(3), [0.0, 0.0, 0.15])
    robot = URRobot("192.168.1.10", tcp=tcp, stale_timeout_s=0.02)
    assert isinstance(robot, Robot)
    robot.connect()
    assert ("setTcp", [0.0, 0.0, 0.15, 0.0, 0.0, 0.0]) in ctl.calls
    np.testing.assert_allclose(robot.measured_pose(), T_from_ur_pose(ctl.pose), atol=1e-15)
    robot.close()
    robot.close()
    assert "stopScript" in _names(ctl) and "moveL" not in _names(ctl)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("robot_mode", 5, "power it on and release the brakes"),
        ("safety_mode", 3, "protective stop"),
        ("safety_mode", 7, "emergency"),
        ("remote", False, "remote control"),
        ("remote", None, "stopped answering"),  # was a RuntimeError traceback
        ("refuse_connection", True, "cannot connect"),
    ],
)
def test_connect_refuses_a_robot_that_is_not_ready(ctl, field, value, message):
    setattr(ctl, field, value)
    robot = URRobot("192.168.1.10")
    with pytest.raises(HardwareFault, match=message):
        robot.connect()
    assert "moveL" not in _names(ctl)


def test_move_linear_passes_the_ur_pose_and_arrives(ctl):
    robot = URRobot("r", max_speed_mps=0.5)
    robot.connect()
    T = robot.measured_pose()
    T[:3, 3] += [0.02, 0.0, -0.03]
    robot.move_linear(T, 0.2, 1.0)
    move = [c for c in ctl.calls if c[0] == "moveL"][0]
    np.testing.assert_allclose(move[1], ur_pose_from_T(T), atol=0)
    assert move[2:] == (0.2, 1.0, True)  # asynchronous, watched by the driver
    np.testing.assert_allclose(robot.measured_pose(), T, atol=1e-9)  # UR pose near angle pi
    with pytest.raises(InputError, match="speed_mps"):
        robot.move_linear(T, 0.8, 1.0)


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("protective_stop", "protective stop"),
        ("estop", "emergency-stop button"),
        ("raise", "script is not running"),
        ("disconnect", "connection to the robot was lost"),
        ("no_motion", "mm and 0.00 deg away"),
    ],
)
def test_failed_move_stops_and_raises(ctl, kind, message):
    robot = URRobot("r")
    robot.connect()
    T = robot.measured_pose()
    T[:3, 3] += [0.0, 0.05, 0.0]
    ctl.next_move = kind
    with pytest.raises(HardwareFault, match=message):
        robot.move_linear(T, 0.1, 1.0)
    # the driver stops the robot, unless the link is gone: then nothing can be sent (ur-rtde's
    # stopL would wait 300 s) and the controller ends the checked move it was given
    assert ("stopL" in _names(ctl)) == (kind != "disconnect")
    assert "unlockProtectiveStop" not in _names(ctl)  # unattended: never recover by itself


def test_lost_connection_never_reports_a_stale_pose(ctl):
    robot = URRobot("r")
    robot.connect()
    robot.measured_pose()
    ctl.connected = False  # the receive interface keeps returning the last pose
    with pytest.raises(HardwareFault, match="lost the RTDE connection"):
        robot.measured_pose()
    with pytest.raises(HardwareFault, match="lost the RTDE connection"):
        robot.move_linear(T_from_ur_pose(ctl.pose), 0.1, 1.0)
    assert "moveL" not in _names(ctl)


def test_frozen_timestamp_is_stale(ctl):
    robot = URRobot("r", stale_timeout_s=0.02)
    robot.connect()
    robot.measured_pose()
    ctl.frozen = True  # isConnected() still True, but no new data
    with pytest.raises(HardwareFault, match="no new data"):
        robot.measured_pose()
    ctl.frozen = False
    robot.measured_pose()


def test_is_reachable_uses_controller_ik_and_safety_limits(ctl):
    robot = URRobot("r", model="UR5e")
    robot.connect()
    T = robot.measured_pose()
    assert robot.is_reachable(T)
    ik_call = [c for c in ctl.calls if c[0] == "getInverseKinematics"][-1]
    np.testing.assert_allclose(ik_call[2], Q0)  # near the current joints
    ctl.unreachable = True
    n_ik = sum(c[0] == "getInverseKinematics" for c in ctl.calls)
    assert not robot.is_reachable(T)
    # the has-solution query answers first: get_inverse_kin is never called on an unreachable
    # pose (on a controller it raises and stops the control script)
    assert sum(c[0] == "getInverseKinematics" for c in ctl.calls) == n_ik
    ctl.unreachable = False
    ctl.outside_safety = True
    assert not robot.is_reachable(T)
    ctl.outside_safety = False
    q_wrist = Q0.copy()
    q_wrist[4] = 0.01
    ctl.q = q_wrist
    assert not robot.is_reachable(urk.fk(q_wrist))  # singular: rejected with a model given


def test_stop_is_safe_any_time_and_wait_settled(ctl):
    robot = URRobot("r")
    robot.stop()  # not connected: nothing to do, no error
    robot.connect()
    robot.stop()
    assert ("stopL", 10.0) in ctl.calls
    robot.wait_settled(0.0)
    with pytest.raises(InputError):
        robot.wait_settled(-1.0)


def test_not_connected_and_missing_library(monkeypatch):
    robot = URRobot("r")
    with pytest.raises(HardwareFault, match="connect"):
        robot.measured_pose()
    monkeypatch.setitem(sys.modules, "rtde_receive", None)  # import now fails
    with pytest.raises(HardwareFault, match="pip install ur-rtde"):
        robot.connect()


def test_a_paused_program_is_not_stopped_without_consent(ctl):
    """The dashboard's ``running`` says False for a paused program, but ur-rtde's upload on
    port 30003 ends it all the same: the old driver connected and ended it."""
    ctl.paused = "glue.urp"
    with pytest.raises(HardwareFault, match=r"a program is running .*PAUSED glue.urp.*"
                       "take_control: true"):
        URRobot("r").connect()
    assert "RTDEControlInterface" not in _names(ctl)
    robot = URRobot("r", take_control=True)
    robot.connect()
    assert robot.controller_info["program_stopped"] == "PAUSED glue.urp"


def test_a_program_started_after_the_dashboard_check_is_not_stopped(ctl):
    ctl.runtime_state = 2  # RTDE says playing, the dashboard had said stopped
    with pytest.raises(HardwareFault, match="runtime state playing"):
        URRobot("r").connect()
    assert "RTDEControlInterface" not in _names(ctl)


def test_a_controller_that_does_not_give_its_tcp_is_a_hardware_fault(ctl):
    ctl.tcp_offset_fails = True  # ur-rtde raises RuntimeError: was a traceback
    with pytest.raises(HardwareFault, match="did not give its TCP offset"):
        URRobot("r").connect()
    assert "stopScript" in _names(ctl)  # closed again
    URRobot("r", tcp=np.eye(4)).connect()  # a cell that sets the TCP never asks


def test_a_stopped_control_script_is_not_an_unreachable_pose(ctl):
    """isPoseWithinSafetyLimits answers False when its command fails (the script stopped,
    e.g. after a fault): the old driver called every pose unreachable."""
    robot = URRobot("r")
    robot.connect()
    T = robot.measured_pose()
    ctl.script_running = False
    with pytest.raises(HardwareFault, match="reachability query .* failed"):
        robot.is_reachable(T)
    ctl.script_running, ctl.outside_safety = True, True
    assert not robot.is_reachable(T)  # a real "no"


@pytest.mark.parametrize("module", ["rtde_receive", "rtde_control", "dashboard_client"])
def test_the_fakes_match_the_installed_ur_rtde(monkeypatch, module):
    """Every method of the fakes exists in ur-rtde with the parameters the fake takes (names
    and order, from the pybind11 signatures of the installed modules)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from pybind_signatures import check_callable, overloads

    real_module = pytest.importorskip(module)  # before the fakes take its place
    install_fakes(monkeypatch, FakeController())
    fake = FAKES[module]
    real = getattr(real_module, fake.__name__)
    methods = [k for k, v in vars(fake).items() if callable(v) and (not k.startswith("_")
                                                                     or k == "__init__")]
    assert len(methods) >= 5
    for name, flag in vars(getattr(fake, "Flags", types.SimpleNamespace())).items():
        assert int(getattr(real.Flags, name)) == flag, name
    for name in methods:
        assert hasattr(real, name), f"{module}.{fake.__name__}.{name} is not in ur-rtde"
        assert overloads(getattr(real, name), name), name  # introspectable: really checked
        check_callable(vars(fake)[name], getattr(real, name), name,
                       f"{module}.{fake.__name__}.{name}")


def test_the_upper_register_range_is_a_cell_option(ctl):
    """Issue 36 item 6: ``robot.upper_range_registers`` reaches the driver, checked."""
    from slidecal.drivers.ur import cell_options

    assert cell_options({"upper_range_registers": True})["upper_range_registers"] is True
    assert cell_options({})["upper_range_registers"] is False
    with pytest.raises(InputError, match="true or false") as e:
        cell_options({"upper_range_registers": "yes"})
    assert e.value.where == "robot.upper_range_registers"

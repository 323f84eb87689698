"""URRobot end to end through the REAL ur-rtde client against a fake controller on loopback.

The fake (``tests/ur_fake_controller.py``) runs in another process: the ur-rtde constructors
hold the GIL while they block. It binds 127.0.0.1 on 30004/30003/29999; a taken port fails the
test with the fake's message. Every wait is bounded: the fake's answers (select with a
time-out), the driver's close (a daemon thread joined with a time-out; the ur-rtde methods
release the GIL) and the fake's exit (killed in the fixture teardown).
"""

from __future__ import annotations

import json
import select
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from slidecal.drivers.ur import URRobot
from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.solver.errors import HardwareFault
from slidecal.solver.geometry import R_from_rvec, T_from_Rt

rtde_control = pytest.importorskip("rtde_control")

FAKE = Path(__file__).with_name("ur_fake_controller.py")
FREQ_HZ = 125.0  # CB3 rate: a quarter of the e-Series load on the shared CPUs
#: The fake sends the exact doubles it holds; what is left is float64 round-off of the pose
#: algebra (axis-angle <-> matrix, TCP composition).
POSE_TOL = 1e-9


class Fake:
    """A fake controller process and its stdin/stdout control channel."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(FAKE)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            text=True,
        )
        first = self._read(15.0)
        if "error" in first:
            self.kill()
            pytest.fail(f"the fake UR controller did not start: {first['error']}")

    def _read(self, timeout_s: float) -> dict:
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout_s)
        if not ready:
            self.kill()
            pytest.fail(f"the fake UR controller did not answer within {timeout_s} s")
        line = self.proc.stdout.readline()
        if not line:
            self.kill()
            pytest.fail(f"the fake UR controller exited (code {self.proc.poll()})")
        return json.loads(line)

    def ctl(self, cmd: str) -> dict:
        self.proc.stdin.write(cmd + "\n")
        self.proc.stdin.flush()
        return self._read(5.0)

    def state(self) -> dict:
        return self.ctl("state")

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(5.0)


@pytest.fixture
def fake():
    f = Fake()
    try:
        yield f
    finally:
        f.kill()


def bounded(fn, timeout_s: float) -> float:
    """Run ``fn`` in a daemon thread; fail the test if it has not returned in ``timeout_s``."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            fn()
        except BaseException as e:  # re-raised in the test's thread
            errors.append(e)

    t0 = time.monotonic()
    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(timeout_s)
    if th.is_alive():
        pytest.fail(f"{getattr(fn, '__name__', fn)} did not return within {timeout_s} s")
    if errors:
        raise errors[0]
    return time.monotonic() - t0


@pytest.fixture
def robot(fake):
    r = URRobot("127.0.0.1", frequency=FREQ_HZ)
    r.connect()
    try:
        yield r
    finally:
        bounded(r.close, 10.0)


def wait_until(pred, timeout_s: float, what: str) -> float:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            pytest.fail(f"{what} did not happen within {timeout_s} s")
        time.sleep(0.02)
    return time.monotonic() - t0


def assert_pose_close(T: np.ndarray, T_ref: np.ndarray, tol: float = POSE_TOL) -> None:
    np.testing.assert_allclose(T[:3, 3], T_ref[:3, 3], atol=tol)
    np.testing.assert_allclose(T[:3, :3], T_ref[:3, :3], atol=tol)


def shifted(T: np.ndarray, dx_m: float, dy_m: float, dz_m: float, rz_deg: float = 0.0):
    """``T`` translated in the base frame and turned about its own z axis."""
    out = T.copy()
    out[:3, 3] += [dx_m, dy_m, dz_m]
    out[:3, :3] = T[:3, :3] @ R_from_rvec([0.0, 0.0, np.radians(rz_deg)])
    return out


# --------------------------------------------------------------------------------- tests
def test_connect_tcp_measured_pose_and_clean_close(fake):
    T_flange_tcp = T_from_Rt(R_from_rvec([0.0, 0.1, 0.0]), [0.01, 0.0, 0.15])
    robot = URRobot("127.0.0.1", frequency=FREQ_HZ, tcp=T_flange_tcp)
    robot.connect()
    st = fake.state()
    # the real client asked the dashboard what URRobot and its constructor need, uploaded
    # the control script once, and set the TCP through the register protocol (SET_TCP = 29)
    assert {"PolyscopeVersion", "is in remote control", "get serial number"} <= set(
        st["dashboard"]
    )
    assert st["script_uploads"] == 1 and st["runtime_state"] == 2
    assert st["commands"] == [29]
    np.testing.assert_allclose(st["tcp"], ur_pose_from_T(T_flange_tcp), atol=1e-12)
    # measured_pose is the fake's TCP pose (flange pose composed with the TCP it was given)
    T = robot.measured_pose()
    assert_pose_close(T, T_from_ur_pose(st["tcp_pose"]))
    assert_pose_close(T, T_from_ur_pose(st["flange_pose"]) @ T_flange_tcp)
    elapsed = bounded(robot.close, 10.0)
    robot.close()  # idempotent
    st = fake.state()
    assert st["commands"][-1] == 255 and st["runtime_state"] == 1  # STOP_SCRIPT over RTDE
    assert not st["moving"]
    wait_until(lambda: not fake.state()["connections"], 3.0, "all client sockets closing")
    assert elapsed < 5.0


def test_move_linear_arrives_and_wait_settled_waits_for_rest(fake, robot):
    T0 = robot.measured_pose()
    T1 = shifted(T0, 0.03, -0.02, 0.01, rz_deg=5.0)
    speed_mps = 0.2
    t0 = time.monotonic()
    robot.move_linear(T1, speed_mps, 1.0)
    took_s = time.monotonic() - t0
    expected_s = np.linalg.norm([0.03, -0.02, 0.01]) / speed_mps  # 0.19 s on the fake
    assert took_s >= 0.9 * expected_s  # blocking: returned after the fake's motion ended
    assert_pose_close(robot.measured_pose(), T1)
    st = fake.state()
    assert_pose_close(T_from_ur_pose(st["tcp_pose"]), T1)
    assert st["commands"][-1] == 3 and not st["moving"]  # MOVEL = 3, done
    # an asynchronous move through the real client: wait_settled must wait for rest
    T2 = shifted(T1, -0.06, 0.0, 0.0)
    assert robot._control.moveL(ur_pose_from_T(T2), speed_mps, 1.0, True)
    t0 = time.monotonic()
    robot.wait_settled(0.05)
    settled_s = time.monotonic() - t0
    assert settled_s >= 0.8 * (0.06 / speed_mps) + 0.05
    assert_pose_close(robot.measured_pose(), T2)


def test_is_reachable_through_controller_calls(fake, robot):
    T = robot.measured_pose()
    assert robot.is_reachable(shifted(T, 0.05, 0.0, 0.0))
    below = shifted(T, 0.0, 0.0, -T[2, 3] - 0.05)  # reachable, under the fake's z = 0 limit
    assert not robot.is_reachable(below)
    assert fake.state()["commands"][-2:] == [30, 36]  # IK with qnear, then the safety check
    robot.move_linear(shifted(T, 0.01, 0.0, 0.0), 0.1, 1.0)  # the script still runs


def test_an_unreachable_pose_does_not_break_the_next_move(fake, robot):
    T = robot.measured_pose()
    assert not robot.is_reachable(shifted(T, 5.0, 0.0, 0.0))
    robot.move_linear(shifted(T, 0.01, 0.0, 0.0), 0.1, 1.0)


def test_protective_stop_during_a_move_raises_and_stops(fake, monkeypatch):
    calls: list[tuple] = []

    class RecordingControl(rtde_control.RTDEControlInterface):
        def stopL(self, *args):
            calls.append(("stopL", *args))
            return super().stopL(*args)

    monkeypatch.setattr(rtde_control, "RTDEControlInterface", RecordingControl)
    robot = URRobot("127.0.0.1", frequency=FREQ_HZ)
    robot.connect()
    try:
        T0 = robot.measured_pose()
        T1 = shifted(T0, 0.04, 0.0, 0.0)
        assert fake.ctl("pstop") == {"ok": "pstop"}
        t0 = time.monotonic()
        with pytest.raises(HardwareFault, match="protective stop"):
            robot.move_linear(T1, 0.2, 1.0)
        # reacts within seconds (the client itself can wait up to 300 s); generous for a busy CI
        assert time.monotonic() - t0 < 5.0
        assert calls == [("stopL", 10.0)]
        st = fake.state()
        assert st["safety_mode"] == 3 and st["runtime_state"] == 1
        # the fake stopped the arm halfway; the client never put stopL on the wire (it returns
        # at once when the script is not running), and the driver did not unlock by itself
        assert st["commands"] == [3]
        assert "unlock protective stop" not in st["dashboard"]
        T_half = T0.copy()
        T_half[:3, 3] = 0.5 * (T0[:3, 3] + T1[:3, 3])
        assert_pose_close(T_from_ur_pose(st["tcp_pose"]), T_half)
    finally:
        assert bounded(robot.close, 10.0) < 8.0


@pytest.mark.parametrize("how", ["drop", "freeze"])
def test_lost_connection_never_returns_a_stale_pose(fake, how):
    robot = URRobot("127.0.0.1", frequency=FREQ_HZ)
    robot.connect()
    try:
        T = robot.measured_pose()
        assert fake.ctl(how) == {"ok": how}
        with pytest.raises(HardwareFault, match="no new data|lost the RTDE connection"):
            robot.measured_pose()
        if how == "freeze":  # a silent loss: the client still says connected, data stale
            assert robot._receive.isConnected()
            with pytest.raises(HardwareFault, match="no new data"):
                robot.measured_pose()
        # the client notices (end of file at once, or its 2.5 s read time-out)
        wait_until(lambda: not robot._receive.isConnected(), 5.0, "isConnected() turning False")
        np.testing.assert_allclose(robot._receive.getActualTCPPose(), ur_pose_from_T(T), atol=1e-12)
        with pytest.raises(HardwareFault, match="lost the RTDE connection"):
            robot.measured_pose()
        with pytest.raises(HardwareFault, match="lost the RTDE connection"):
            robot.move_linear(shifted(T, 0.01, 0.0, 0.0), 0.1, 1.0)
    finally:
        wait_until(lambda: not robot._control.isConnected(), 5.0, "control link giving up")
        assert bounded(robot.close, 10.0) < 8.0


@pytest.mark.parametrize("how", ["drop", "freeze"])
def test_link_lost_during_a_move_fails_within_seconds(fake, how):
    """A blocking moveL would wait up to 300 s inside ur-rtde; the driver watches the move."""
    robot = URRobot("127.0.0.1", frequency=FREQ_HZ)
    robot.connect()
    try:
        T = robot.measured_pose()
        cut = threading.Timer(0.3, fake.ctl, args=(how,))  # mid-move: the move takes ~2 s
        cut.start()
        t0 = time.monotonic()
        with pytest.raises(HardwareFault, match="no new data|lost the RTDE connection"):
            robot.move_linear(shifted(T, 0.2, 0.0, 0.0), 0.1, 1.0)
        assert time.monotonic() - t0 < 5.0
        cut.join(5.0)
    finally:
        wait_until(lambda: not robot._control.isConnected(), 5.0, "control link giving up")
        assert bounded(robot.close, 10.0) < 8.0


def test_a_taken_port_fails_clearly(fake):
    second = subprocess.run(
        [sys.executable, str(FAKE)], stdin=subprocess.DEVNULL, capture_output=True, text=True,
        timeout=20,
    )
    assert second.returncode == 2
    assert "port 30004 (rtde) on 127.0.0.1 is taken" in json.loads(second.stdout)["error"]

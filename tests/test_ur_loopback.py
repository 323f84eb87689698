"""URRobot end to end through the REAL ur-rtde client against the loopback controller.

The controller (``slidecal.mocks.ur_controller``) runs in another process: the ur-rtde
constructors hold the GIL while they block. Each controller binds its own loopback address
127.<pid>.<n> on 30004/30003/29999, so parallel test runs do not collide; a taken port fails
the test with the controller's message. Tests that only move relative to the pose they find
share a controller and a connection (class fixtures): ur-rtde's ``disconnect`` ends in a fixed
0.5 s wait and its destructors call it again, so every close costs about 2 s. Every wait is
bounded: the controller's answers (select with a time-out), the driver's close (a daemon thread
joined with a time-out; the ur-rtde methods release the GIL) and the controller's exit (killed
in the fixture teardown). What could block inside a ur-rtde constructor runs in a subprocess
with a time-out.
"""

from __future__ import annotations

import itertools
import json
import os
import select
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from slidecal.drivers.ur import URRobot
from slidecal.drivers.ur_pose import T_from_ur_pose, ur_pose_from_T
from slidecal.solver.errors import HardwareFault
from slidecal.solver.geometry import R_from_rvec, T_from_Rt

rtde_control = pytest.importorskip("rtde_control")

CONTROLLER = [sys.executable, "-m", "slidecal.mocks.ur_controller"]
_hosts = itertools.count(1)


def fresh_host() -> str:
    """A loopback address of its own for one controller (Linux routes all of 127/8 to lo)."""
    n = next(_hosts)
    return f"127.{os.getpid() % 250 + 1}.{n // 250}.{n % 250 + 1}"
FREQ_HZ = 125.0  # CB3 rate: a quarter of the e-Series load on the shared CPUs
#: The fake sends the exact doubles it holds; what is left is float64 round-off of the pose
#: algebra (axis-angle <-> matrix, TCP composition).
POSE_TOL = 1e-9


class Fake:
    """A fake controller process and its stdin/stdout control channel."""

    def __init__(self, *options: str, host: str | None = None) -> None:
        self.host = host or fresh_host()
        self.proc = subprocess.Popen(
            [*CONTROLLER, "--host", self.host, *options], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, text=True,
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


@pytest.fixture
def make_fake():
    """Start controllers with options; all are killed at the end of the test."""
    fakes: list[Fake] = []

    def start(*options: str) -> Fake:
        fakes.append(Fake(*options))
        return fakes[-1]

    try:
        yield start
    finally:
        for f in fakes:
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


@pytest.fixture(scope="class")
def shared():
    """(controller, connected URRobot) for the tests that only move relative to the pose they
    find and query (see the module docstring)."""
    f = Fake()
    try:
        r = URRobot(f.host, frequency=FREQ_HZ, stale_timeout_s=1.0)  # 1.0 s: see ``robot``
        r.connect()
        try:
            yield f, r
        finally:
            bounded(r.close, 10.0)
    finally:
        f.kill()


@pytest.fixture
def robot(fake):
    # the fake controller is a Python thread: on a machine busy with other work it can stall
    # for more than the driver's 0.1 s (seen: a pure-rotation test failed with "no new data
    # for 0.1 s" while benchmarks ran). Motion tests are not about that; the staleness tests
    # build their own robot with the driver's default.
    r = URRobot(fake.host, frequency=FREQ_HZ, stale_timeout_s=1.0)
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
    robot = URRobot(fake.host, frequency=FREQ_HZ, tcp=T_flange_tcp)
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


class TestOneConnection:
    """Moves and queries relative to the pose each test finds, on one connection."""

    def test_move_linear_arrives_and_wait_settled_waits_for_rest(self, shared):
        fake, robot = shared
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
        t0 = time.monotonic()
        assert robot._control.moveL(ur_pose_from_T(T2), speed_mps, 1.0, True)
        # the controller starts the motion a few cycles after acknowledging the command
        wait_until(lambda: np.linalg.norm(robot._receive.getActualTCPSpeed()) > 0, 1.0, "motion")
        robot.wait_settled(0.05)
        settled_s = time.monotonic() - t0
        assert settled_s >= 0.8 * (0.06 / speed_mps) + 0.05
        assert_pose_close(robot.measured_pose(), T2)

    def test_is_reachable_through_controller_calls(self, shared):
        fake, robot = shared
        T = robot.measured_pose()
        assert robot.is_reachable(shifted(T, 0.05, 0.0, 0.0))
        below = shifted(T, 0.0, 0.0, -T[2, 3] - 0.05)  # reachable, under the fake's z = 0 limit
        assert not robot.is_reachable(below)
        assert fake.state()["commands"][-2:] == [30, 36]  # IK with qnear, then the safety check
        robot.move_linear(shifted(T, 0.01, 0.0, 0.0), 0.1, 1.0)  # the script still runs

    def test_an_unreachable_pose_does_not_break_the_next_move(self, shared):
        _, robot = shared
        T = robot.measured_pose()
        assert not robot.is_reachable(shifted(T, 5.0, 0.0, 0.0))
        robot.move_linear(shifted(T, 0.01, 0.0, 0.0), 0.1, 1.0)

    def test_sigterm_during_a_move_stops_the_arm_through_the_real_client(self, shared):
        """SIGTERM (like Ctrl-C) interrupts the driver's watch of an asynchronous moveL at once;
        the stop the routine then sends (``_abort`` -> ``stop()`` -> ``stopL``) goes through the
        real ur-rtde client and halts the arm short of its target."""
        from slidecal.routines.progress import Interrupted, signals_as_interrupt

        fake, robot = shared
        n_before = len(fake.state()["commands"])
        T0 = robot.measured_pose()
        T1 = shifted(T0, 0.15, 0.0, 0.0)  # 1.5 s at 0.1 m/s
        timer = threading.Timer(0.4, os.kill, (os.getpid(), signal.SIGTERM))
        t0 = time.monotonic()
        with signals_as_interrupt(), pytest.raises(Interrupted, match="SIGTERM"):
            timer.start()
            robot.move_linear(T1, 0.1, 1.0)
        assert time.monotonic() - t0 < 1.2  # interrupted, not waited out
        robot.stop()
        st = fake.state()
        assert 33 in st["commands"][n_before:] and not st["moving"]  # STOPL reached the controller
        x_now = T_from_ur_pose(st["tcp_pose"])[0, 3]
        assert T0[0, 3] + 0.005 < x_now < T1[0, 3] - 0.05  # moved, and stopped well short
        time.sleep(0.3)
        assert np.allclose(fake.state()["tcp_pose"], st["tcp_pose"], atol=1e-9)  # at rest


def test_protective_stop_during_a_move_raises_and_stops(fake, monkeypatch):
    calls: list[tuple] = []

    class RecordingControl(rtde_control.RTDEControlInterface):
        def stopL(self, *args):
            calls.append(("stopL", *args))
            return super().stopL(*args)

    monkeypatch.setattr(rtde_control, "RTDEControlInterface", RecordingControl)
    robot = URRobot(fake.host, frequency=FREQ_HZ)
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
        assert st["commands"] == [40, 3]  # GET_TCP_OFFSET at connect, MOVEL
        assert "unlock protective stop" not in st["dashboard"]
        T_half = T0.copy()
        T_half[:3, 3] = 0.5 * (T0[:3, 3] + T1[:3, 3])
        assert_pose_close(T_from_ur_pose(st["tcp_pose"]), T_half)
    finally:
        assert bounded(robot.close, 10.0) < 8.0


@pytest.mark.slow  # several seconds: the second CI tier
@pytest.mark.parametrize("how", ["drop", "freeze"])
def test_lost_connection_never_returns_a_stale_pose(fake, how):
    robot = URRobot(fake.host, frequency=FREQ_HZ)
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


@pytest.mark.slow  # several seconds: the second CI tier
@pytest.mark.parametrize("how", ["drop", "freeze"])
def test_link_lost_during_a_move_fails_within_seconds(fake, how):
    """A blocking moveL would wait up to 300 s inside ur-rtde; the driver watches the move."""
    robot = URRobot(fake.host, frequency=FREQ_HZ)
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
        [*CONTROLLER, "--host", fake.host], stdin=subprocess.DEVNULL, capture_output=True,
        text=True, timeout=20,
    )
    assert second.returncode == 2
    assert f"port 30004 (rtde) on {fake.host} is taken" in json.loads(second.stdout)["error"]


# ------------------------------------------------------------- issue 10: a real cell's controller
# the oldest (CB3) and the newest in the fast tier, the two between in the slow one
VERSIONS = [
    "3.15",
    pytest.param("5.5", marks=pytest.mark.slow),
    pytest.param("5.9", marks=pytest.mark.slow),
    "5.12",
]


@pytest.fixture(scope="class", params=VERSIONS)
def version_robot(request):
    """(PolyScope version, its controller, URRobot connected to it), shared by the tests of one
    version (see the module docstring)."""
    version = request.param
    fake = Fake("--polyscope", version)
    try:
        robot = URRobot(fake.host, frequency=FREQ_HZ, model="UR5e")
        robot.connect()
        try:
            yield version, fake, robot
        finally:
            bounded(robot.close, 10.0)
    finally:
        fake.kill()


class TestEveryPolyScopeVersion:
    """One connection per version, shared by its tests."""

    def test_connect_on_every_polyscope_version_and_report_it(self, version_robot):
        """CB3 and e-Series below 5.6 cannot say whether they are in remote control (ur-rtde's
        isInRemoteControl answers False there): connecting must not refuse them (issue 10.3)."""
        version, _, robot = version_robot
        info = robot.controller_info
        assert info["polyscope_version"].startswith(version + ".")
        assert info["robot_model"] == "UR5"
        assert info["serial_number"] == (None if version in ("3.15", "5.5") else "20185500001")
        assert info["remote_control"] is (None if version in ("3.15", "5.5") else True)
        assert info["ik_check"] == ("host" if version in ("5.5", "5.9") else "controller")
        robot.move_linear(shifted(robot.measured_pose(), 0.01, 0.0, 0.0), 0.1, 1.0)

    def test_reachability_below_5_10_does_not_trust_a_stale_register(self, version_robot):
        """Without get_inverse_kin_has_solution (ur-rtde drops it below 5.10 / 3.15) the answer
        register keeps the previous answer: a reachable pose then an unreachable one said True,
        and the controller's get_inverse_kin stopped the script (issue 10.5)."""
        version, fake, robot = version_robot
        T = robot.measured_pose()
        assert robot.is_reachable(shifted(T, 0.05, 0.0, 0.0))
        assert not robot.is_reachable(shifted(T, 5.0, 0.0, 0.0))
        below = shifted(T, 0.0, 0.0, -T[2, 3] - 0.05)  # reachable, under the z = 0 limit
        assert not robot.is_reachable(below)
        robot.move_linear(shifted(T, 0.01, 0.0, 0.0), 0.1, 1.0)  # the script still runs
        st = fake.state()
        assert st["runtime_state"] == 2
        assert (61 in st["commands"]) == (version in ("3.15", "5.12"))


def test_local_control_is_refused_where_it_can_be_asked(make_fake):
    fake = make_fake("--polyscope", "5.12", "--local")
    with pytest.raises(HardwareFault, match="local control"):
        URRobot(fake.host, frequency=FREQ_HZ).connect()
    assert fake.state()["script_uploads"] == 0


@pytest.mark.slow  # several seconds: the second CI tier
def test_a_running_program_is_not_stopped_without_consent(make_fake):
    """ur-rtde's control interface stops a running program and uploads its own (issue 10.4)."""
    fake = make_fake("--program", "palletizing.urp")
    with pytest.raises(HardwareFault, match=r"program is running.*palletizing.urp.*take_control"):
        URRobot(fake.host, frequency=FREQ_HZ).connect()
    st = fake.state()
    assert st["program"] == "palletizing.urp" and st["script_uploads"] == 0
    assert "stop" not in st["dashboard"]
    robot = URRobot(fake.host, frequency=FREQ_HZ, take_control=True)
    robot.connect()
    try:
        assert "palletizing.urp" in robot.controller_info["program_stopped"]
        assert fake.state()["program"] is None
    finally:
        bounded(robot.close, 10.0)


def test_reduced_mode_is_normal_operation_and_the_payload_is_set(make_fake):
    fake = make_fake("--safety-mode", "2")
    robot = URRobot(fake.host, frequency=FREQ_HZ, payload_kg=1.2, payload_cog_m=[0, 0.01, 0.05])
    robot.connect()
    try:
        robot.move_linear(shifted(robot.measured_pose(), 0.02, 0.0, 0.0), 0.1, 1.0)
        st = fake.state()
        assert st["payload"] == [1.2, [0.0, 0.01, 0.05]]
        assert robot.controller_info["safety_mode"] == "reduced mode"
        assert fake.ctl("safety 3") == {"ok": "safety 3"}
        with pytest.raises(HardwareFault, match="protective stop"):
            robot.move_linear(shifted(robot.measured_pose(), 0.02, 0.0, 0.0), 0.1, 1.0)
    finally:
        bounded(robot.close, 10.0)


def test_the_slider_is_reported_as_a_controller_reports_it(make_fake):
    """Issue 36 item 2. On a controller the pendant's slider is ``target_speed_fraction``;
    ``speed_scaling`` is the trajectory limiter's factor; ur-rtde's
    ``getSpeedScalingCombined`` is their product (``rtde_receive_interface.cpp``). Read here
    through the real client, so the loopback cannot agree with the driver on anything else."""
    import rtde_receive

    fake = make_fake("--speed-slider", "0.2")
    receive = rtde_receive.RTDEReceiveInterface(fake.host, FREQ_HZ)
    try:
        assert receive.getTargetSpeedFraction() == pytest.approx(0.2)
        assert receive.getSpeedScaling() == pytest.approx(1.0)
        assert receive.getSpeedScalingCombined() == pytest.approx(0.2)
    finally:
        receive.disconnect()


@pytest.mark.slow  # several seconds: the second CI tier
def test_a_slow_speed_slider_is_not_a_time_out(make_fake):
    """At a 20 % slider a 5 cm move takes 2.5 s: the deadline from the commanded speed alone
    (2 x 0.6 s + 1 s) aborted it (issue 10.6), and so did one from the trajectory limiter's
    ``getSpeedScaling`` (1 while the slider is at 20 %: issue 36 item 2)."""
    fake = make_fake("--speed-slider", "0.2")
    robot = URRobot(fake.host, frequency=FREQ_HZ, settle_timeout_s=1.0)
    robot.connect()
    try:
        T1 = shifted(robot.measured_pose(), 0.05, 0.0, 0.0)
        robot.move_linear(T1, 0.1, 1.0)
        assert_pose_close(T_from_ur_pose(fake.state()["tcp_pose"]), T1)
        assert robot.controller_info["speed_slider"] == pytest.approx(0.2)
    finally:
        bounded(robot.close, 10.0)


@pytest.mark.slow  # several seconds: the second CI tier
def test_pure_rotations_arrive_in_orientation(fake, robot):
    """Arrival judged on position only returned at once from a pure rotation (issue 10.6)."""
    T = robot.measured_pose()
    for k in range(6):
        T_k = shifted(T, 0.0, 0.0, 0.0, rz_deg=10.0 * (k + 1) * (-1) ** k)
        robot.move_linear(T_k, 0.25, 1.0)
        assert_pose_close(T_from_ur_pose(fake.state()["tcp_pose"]), T_k)


def test_a_stalled_arm_is_a_fault_within_the_deadline(fake, robot):
    T = robot.measured_pose()
    assert fake.ctl("stall") == {"ok": "stall"}
    t0 = time.monotonic()
    with pytest.raises(HardwareFault, match="at rest"):
        robot.move_linear(shifted(T, 0.05, 0.0, 0.0), 0.1, 1.0)
    assert time.monotonic() - t0 < 3.0


CONNECT_SCRIPT = textwrap.dedent(
    """
    import sys, time
    from slidecal.drivers.ur import URRobot
    from slidecal.solver.errors import HardwareFault
    t0 = time.monotonic()
    try:
        URRobot(sys.argv[1], frequency=125.0, connect_timeout_s=float(sys.argv[2])).connect()
    except HardwareFault as e:
        print(f"{time.monotonic() - t0:.2f} fault: {e}", flush=True)
        sys.exit(3)
    except KeyboardInterrupt:
        print(f"{time.monotonic() - t0:.2f} interrupted", flush=True)
        sys.exit(130)
    print("connected", flush=True)
    """
)


def test_connect_to_a_host_that_drops_packets_fails_within_seconds(make_fake):
    """ur-rtde's constructors block ~2 minutes on a silent host, deaf to Ctrl-C (issue 10.10);
    run in a subprocess so the old behaviour fails this test instead of hanging it."""
    fake = make_fake("--silent")
    try:
        out = subprocess.run([sys.executable, "-c", CONNECT_SCRIPT, fake.host, "2"],
                             capture_output=True, text=True, timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail("connect() to a silent host did not return within 30 s")
    assert out.returncode == 3, out.stderr
    took_s, _, message = out.stdout.partition(" fault: ")
    assert "not reachable on port 29999 (no answer within 2 s)" in message
    assert float(took_s) < 4.0


def _ctrl_c_as_a_terminal_delivers_it() -> None:
    """In the child before it runs: Ctrl-C's default disposition. A process started in the
    background by a shell without job control (a CI step run with '&', nohup-style) inherits
    SIGINT ignored, and Python then never raises KeyboardInterrupt: the test would hang on the
    harness, not on the driver."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_connect_to_a_silent_host_honours_ctrl_c(make_fake):
    fake = make_fake("--silent")
    proc = subprocess.Popen([sys.executable, "-c", CONNECT_SCRIPT, fake.host, "60"],
                            stdout=subprocess.PIPE, text=True,
                            preexec_fn=_ctrl_c_as_a_terminal_delivers_it)
    try:
        time.sleep(1.5)  # imports done, waiting on the silent host
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail("connect() ignored Ctrl-C for 10 s")
    assert proc.returncode == 130 and "interrupted" in out


def test_cb3_payload_without_cog_keeps_the_controllers_cog(make_fake):
    """Issue 36 item 4. ur-rtde sends [0, 0, 0] for an empty CoG; the script line that keeps
    the current CoG is tagged ``$5.0`` (``rtde_control.script``), so the real client leaves it
    out on 3.x and the CoG would become the flange centre. Through the real client: on 3.15
    the driver reads the CoG (``getPayloadCog``) and sends it back; on 5.12 the script keeps it.
    """
    for version in ("3.15", "5.12"):
        fake = make_fake("--polyscope", version, "--payload-cog", "0,0.01,0.07")
        robot = URRobot(fake.host, frequency=FREQ_HZ, payload_kg=1.2)
        robot.connect()
        try:
            assert fake.state()["payload"] == [1.2, [0.0, 0.01, 0.07]], version
        finally:
            bounded(robot.close, 10.0)


def test_a_script_left_by_a_dropped_link_is_named_on_resume(fake):
    """Issue 36 item 5. Over a dead link the driver does not send stopScript (ur-rtde would
    wait 300 s), so ur-rtde's script keeps playing; the next connect says it is that script
    and what to do, instead of "a program is running"."""
    robot = URRobot(fake.host, frequency=FREQ_HZ)
    robot.connect()
    assert fake.ctl("drop") == {"ok": "drop"}
    bounded(robot.close, 10.0)
    assert fake.ctl("reopen") == {"ok": "reopen"}
    assert fake.state()["runtime_state"] == 2  # the script still plays
    with pytest.raises(HardwareFault, match=r"ur-rtde's control script .* still runs.*lost its "
                       r"link.*stop on the pendant.*take_control: true.*resume"):
        URRobot(fake.host, frequency=FREQ_HZ).connect()
    robot = URRobot(fake.host, frequency=FREQ_HZ, take_control=True)
    robot.connect()
    bounded(robot.close, 10.0)


def test_fieldbus_registers_in_use_are_named_and_the_upper_range_works(make_fake):
    """Issue 36 item 6. A fieldbus holding the RTDE input registers makes the controller
    answer ``IN_USE`` in the input recipe and the real client throw "One of the RTDE input
    registers are already in use!"; the driver says so and offers the upper range, with which
    the real client and the loopback run the register protocol at offset 24."""
    fake = make_fake("--fieldbus")
    with pytest.raises(HardwareFault, match=r"EtherNet/IP, PROFINET or a MODBUS.*"
                       r"upper_range_registers: true"):
        URRobot(fake.host, frequency=FREQ_HZ).connect()
    robot = URRobot(fake.host, frequency=FREQ_HZ, upper_range_registers=True)
    robot.connect()
    try:
        T1 = shifted(robot.measured_pose(), 0.02, 0.0, 0.0)
        robot.move_linear(T1, 0.1, 1.0)
        assert_pose_close(T_from_ur_pose(fake.state()["tcp_pose"]), T1)
    finally:
        bounded(robot.close, 10.0)


def test_the_loopback_measures_how_long_it_went_unscheduled(make_fake):
    """Issue 36 item 3: the loopback reports its longest event-loop gap (what a rehearsal's
    stale-data limit is fitted to), here with a host that stalls it 0.3 s every 0.4 s."""
    assert make_fake().state()["cycle_gap_max_s"] < 0.3
    fake = make_fake("--starve", "0.3,0.4")
    time.sleep(1.0)
    assert fake.state()["cycle_gap_max_s"] >= 0.3

"""Real-hardware cells on fakes: ``slidecal run`` with a UVC cell end to end (a fake
``cv2.VideoCapture`` that plays what the simulated cell renders at the robot's pose); an OAK
cell's settings reaching the cameras, the device report and calibrations in the session, the
comparison and export after a solve, and ``slidecal flash`` (the depthai fake of
``tests/fake_depthai.py``; rendering the three OAK-D images takes too long here for a whole run);
the one-line refusal of a cell whose driver library is missing."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import yaml

pytest.importorskip("depthai")  # the fake is the installed depthai minus the device
sys.path.insert(0, str(Path(__file__).parent))
import fake_depthai  # noqa: E402

from slidecal.mocks.cell import SimulatedCell  # noqa: E402
from slidecal.routines import cli  # noqa: E402
from slidecal.routines.config import load_config, load_packaged_cell  # noqa: E402
from slidecal.routines.devices import camera_rig  # noqa: E402
from slidecal.routines.run import RunRequest, run_calibration  # noqa: E402
from slidecal.routines.session import SessionWriter  # noqa: E402
from slidecal.solver.errors import HardwareFault, InputError  # noqa: E402
from slidecal.solver.result import (  # noqa: E402
    CalibrationResult,
    CameraEstimate,
    TransformEstimate,
)

TARGET = {"kind": "charuco", "squares_x": 11, "squares_y": 8, "square_size_m": 0.030,
          "marker_size_m": 0.022, "dictionary": "DICT_5X5_100"}


def real_cell(packaged: str, cameras: dict) -> dict:
    """A packaged simulated cell turned into a real one: robot at a (documentation) address,
    the given cameras, no simulation block (the approximate geometry stays)."""
    import importlib.resources

    data = yaml.safe_load(
        importlib.resources.files("slidecal.mocks").joinpath(packaged).read_text()
    )
    data["robot"] = {**data["robot"], "driver": "ur", "host": "192.0.2.10"}
    data["robot"].pop("start_pose", None)
    data["cameras"] = cameras
    data.pop("simulation")
    return data


def write_cell(tmp_path, data) -> Path:
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def use_simulated_robot(monkeypatch, cell):
    import slidecal.routines.acquire as acquire

    monkeypatch.setattr(acquire, "URRobot", lambda *a, **k: cell.robot)


# ---------------------------------------------------------------------------------- UVC cell


class RenderingCapture:
    """cv2.VideoCapture playing what the simulated camera sees at the robot's pose now."""

    rig = None
    instances: list = []

    def __init__(self, source, apiPreference=cv2.CAP_ANY):  # noqa: N803 - OpenCV's name
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 640.0, cv2.CAP_PROP_FRAME_HEIGHT: 480.0,
                      cv2.CAP_PROP_AUTOFOCUS: 1.0}
        self.image = None
        self.rig.open()
        RenderingCapture.instances.append(self)

    def isOpened(self):
        return True

    def getBackendName(self):
        return "V4L2"

    def set(self, prop, value):
        self.props[prop] = float(value)
        return True

    def get(self, prop):
        return self.props.get(prop, -1.0)

    def grab(self):
        self.image = None
        return True

    def retrieve(self):
        if self.image is None:
            self.image = next(iter(self.rig.capture().values()))
        return True, self.image

    def release(self):
        self.rig.close()


def uvc_cell(tmp_path, monkeypatch, **camera):
    """The default cell with a UVC camera that renders the simulated one (seed 3), its robot
    simulated: (the simulated cell, the real cell file)."""
    cell = SimulatedCell.from_config(load_config(None), seed=3)
    use_simulated_robot(monkeypatch, cell)
    RenderingCapture.rig, RenderingCapture.instances = cell.rig, []
    monkeypatch.setattr(cv2, "VideoCapture", RenderingCapture)
    spec = cell.rig.specs[0]
    cameras = {"driver": "uvc", "list": [{"name": spec.name, "width": spec.width,
                                          "height": spec.height, "source": 0, **camera}]}
    return cell, write_cell(tmp_path, real_cell("default_cell.yaml", cameras))


@pytest.mark.slow
def test_a_uvc_cell_runs_end_to_end(tmp_path, monkeypatch):
    cell, path = uvc_cell(tmp_path, monkeypatch, exposure=150, drop_frames=1)
    spec = cell.rig.specs[0]
    out = run_calibration(RunRequest(path, out_dir=tmp_path / "s", progress=False, recording=False))
    session = yaml.safe_load((out.session_dir / "session.yaml").read_text())
    cam = session["devices"]["camera"]
    assert cam["driver"] == "uvc" and cam["backend"] == "V4L2"
    assert cam["settings"]["autofocus"]["read_back"] == 0.0
    assert cam["settings"]["exposure"] == {"requested": 150.0, "read_back": 150.0,
                                           "accepted": True}
    assert session["status"] == "complete" and out.n_frames == len(session["frames"])
    # the calibration is the simulated camera's, within the reported uncertainty
    est = out.result.cameras[spec.name]
    truth = np.asarray(cell.truth["cameras"][spec.name]["K"])
    for label, (i, j) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2)}.items():
        assert abs(est.K[i][j] - truth[i, j]) < 5 * est.std[label] + 0.05, label


def test_a_stopped_uvc_run_resumes(tmp_path, monkeypatch):
    """A real rig reports itself into a resumed session as into a new one (the resume was
    refused: the session directory "already holds a session")."""
    cell, path = uvc_cell(tmp_path, monkeypatch)
    cell.robot.inject_fault("protective_stop", 4)
    with pytest.raises(HardwareFault):
        run_calibration(RunRequest(path, out_dir=tmp_path / "s", progress=False, recording=False))
    cell.robot.clear_fault()
    out = run_calibration(RunRequest(path, resume=tmp_path / "s", progress=False))
    session = yaml.safe_load((out.session_dir / "session.yaml").read_text())
    assert session["status"] == "complete" and out.n_frames == len(session["frames"])
    assert session["devices"]["camera"]["driver"] == "uvc"


# ---------------------------------------------------------------------------------- OAK cell


def truth_result(cfg, dfx_left_px: float = 0.0) -> CalibrationResult:
    """The simulated OAK-D's truth as a result (``dfx_left_px`` added to the left fx)."""
    cams = {}
    for c in cfg.simulation.cameras:
        K = np.array(c.K, float)
        K[0, 0] += dfx_left_px if c.name == "left" else 0.0
        cams[c.name] = CameraEstimate(c.name, c.width, c.height, K, c.dist, {}, 0.0)
    rig = {f"T_{n}_left": TransformEstimate(f"T_{n}_left", T[:3, :3], T[:3, 3])
           for n, T in cfg.simulation.rig.items()}
    return CalibrationResult(
        cameras=cams, hand_eye=None, rig=rig, T_target=None, converged=True, iterations=0,
        reproj_rms_px=0.0, sigma_px=0.0, parameter_names=(), covariance=None, residuals_px={},
        outliers=(), unobservable={}, messages=(), reference_camera="left",
    )


OAK_CAMERAS = {
    "driver": "oak", "reference": "left", "fps": 10, "exposure_us": 8000, "iso": 400,
    "list": [
        {"name": "left", "width": 1280, "height": 800, "socket": "CAM_B"},
        {"name": "right", "width": 1280, "height": 800, "socket": "CAM_C"},
        {"name": "rgb", "width": 1920, "height": 1080, "socket": "CAM_A", "colour": True,
         "focus": 130},
    ],
}


def norm(data):
    """depthai calibration JSON with its camera list as a dict (its order is not kept)."""
    return {**data, "cameraData": {int(k): v for k, v in data["cameraData"]}}


@pytest.fixture
def oak_device(monkeypatch):
    """The fake OAK-D holding the simulated truth as its factory and user calibration."""
    from slidecal.drivers.oak import oak_calibration_handler

    world = fake_depthai.World()
    sim = load_packaged_cell("oak_cell.yaml")
    world.factory = oak_calibration_handler(truth_result(sim), base=world.factory)
    world.user = fake_depthai._copy(world.factory)
    monkeypatch.setitem(sys.modules, "depthai", fake_depthai.make_fake_depthai(world))
    monkeypatch.setattr("slidecal.drivers.oak.AUTO_EXPOSURE_SETTLE_S", 0.05)
    yield world, sim
    for p in world.pipelines:
        p.stop()


def test_the_oak_cell_settings_reach_the_driver(tmp_path, oak_device):
    """Issue 10 item 1: the cell's exposure, ISO, focus (and frame rate, resize) reach the
    cameras' initial controls through the run's connection code."""
    from slidecal.routines.acquire import _connect_real

    world, _ = oak_device
    cfg = load_config(write_cell(tmp_path, real_cell("oak_cell.yaml", OAK_CAMERAS)))
    _, rig = _connect_real(cfg)
    rig.open()
    controls = {c._socket: c.initialControl for c in world.pipelines[0].cameras}
    assert {s: (c.getExposureTime().total_seconds(), c.getSensitivity())
            for s, c in controls.items()} == {s: (0.008, 400) for s in ("CAM_A", "CAM_B", "CAM_C")}
    assert controls["CAM_A"].getLensPosition() == 130
    assert rig.capabilities()["outputs"]["rgb"]["fps"] == 10.0
    rig.close()


def test_an_oak_session_records_the_device_compares_and_flashes(tmp_path, oak_device, capsys):
    from slidecal.drivers.oak import OakRig, device_camera
    from slidecal.routines.devices import device_calibration_outputs, record_devices
    from slidecal.routines.results_io import write_result
    from slidecal.routines.session import SessionWriter

    world, sim = oak_device
    rig = OakRig(focus={"rgb": 130})
    rig.open()
    sdir = tmp_path / "s"
    devices = record_devices(rig, sdir, 0.5)
    rig.close()
    SessionWriter(sdir, sim.target, rig.specs, extra=devices).finish()
    session = yaml.safe_load((sdir / "session.yaml").read_text())
    dev = session["devices"]
    assert dev["camera"]["device_id"] == world.device_id
    assert dev["camera"]["outputs"]["rgb"]["focus"] == 130
    assert dev["calibration_files"] == {"user": "device_calibration_user.json",
                                        "factory": "device_calibration_factory.json"}
    factory = json.loads((sdir / "device_calibration_factory.json").read_text())
    assert factory["boardName"] == "OAK-D"

    # a result whose left fx is 2 px above the device's: the export starts from the device's
    # calibration and the summary says how far points move
    result = truth_result(sim, dfx_left_px=2.0)
    write_result(result, sdir / "result.yaml")
    exports, summary = device_calibration_outputs(result, sdir, sdir / "export")
    export = json.loads((sdir / "export" / "depthai_calibration.json").read_text())
    assert export["boardName"] == "OAK-D" and export["boardRev"] == "R3M2E3"
    assert {int(k): v["lensPosition"] for k, v in export["cameraData"]}[0] == 130  # CAM_A
    line = next(x for x in summary.splitlines() if x.startswith("device factory"))
    K = np.asarray(result.cameras["left"].K)
    x_edge = max(0.95 * 1279 - K[0, 2], K[0, 2] - 0.05 * 1279) / (K[0, 0] - 2.0)
    assert "left 0.00 rms" not in line and f"{2 * x_edge:.2f} max" in line, line
    assert "right 0.00 rms / 0.00 max" in line  # the right camera's calibration is the same

    # slidecal flash: a dry run writes nothing
    before = world.user.eepromToJson()
    assert cli.main(["flash", str(sdir)]) == 0
    assert "nothing written" in capsys.readouterr().out
    assert world.user.eepromToJson() == before and ("flashCalibration",) not in world.calls
    # another device connected: refused
    world.device_id = "OTHER"
    assert cli.main(["flash", str(sdir), "--write"]) == 2
    assert "not 18443010D1E4F1F500" in capsys.readouterr().err
    world.device_id = dev["camera"]["device_id"]
    # a failing write: a hardware fault, and the backup was saved before it
    world.flash_fails = True
    assert cli.main(["flash", str(sdir), "--write"]) == 3
    backups = sorted(sdir.glob("device_calibration_backup_*.json"))
    assert backups and norm(json.loads(backups[-1].read_text())) == norm(before)
    world.flash_fails = False
    # what the device holds afterwards is not what was sent: said, with the backup to restore
    world.flash_corrupts = True
    assert cli.main(["flash", str(sdir), "--write"]) == 3
    assert "differs from what was written" in capsys.readouterr().err
    world.flash_corrupts = False
    assert cli.main(["flash", str(sdir), "--write"]) == 0
    assert "read back identical" in capsys.readouterr().out
    K_dev, _ = device_camera(world.user.eepromToJson(), "CAM_B", (1280, 800))
    np.testing.assert_allclose(K_dev, result.cameras["left"].K, rtol=1e-6)
    assert world.user.eepromToJson()["boardName"] == "OAK-D"
    assert world.user.getLensPosition(fake_depthai.dai.CameraBoardSocket.CAM_A) == 130
    # issue 36 item 1: the colour stream, stretched from the whole 4:3 array, is written at the
    # size the device stores CAM_A at (1080p, a 16:9 crop), as depthai reads it there: fx as
    # the stream's (the crop keeps the width), fy through the stretch and the crop
    A = fake_depthai.dai.CameraBoardSocket.CAM_A
    K_rgb = np.asarray(result.cameras["rgb"].K)
    export = fake_depthai.dai.CalibrationHandler(str(sdir / "export" / "depthai_calibration.json"))
    for h in (world.user, export):
        assert h.getDefaultIntrinsics(A)[1:] == (1920, 1080)
        K = np.asarray(h.getCameraIntrinsics(A, 1920, 1080))
        assert K[0, 0] == pytest.approx(K_rgb[0, 0], rel=1e-6)
        assert K[1, 1] == pytest.approx(K_rgb[1, 1] * 3040 / 1080 * 1920 / 4056, rel=1e-6)


# ---------------------------------------------------------------------- configuration errors


def test_a_missing_driver_library_names_the_extra(tmp_path, monkeypatch, capsys):
    path = write_cell(tmp_path, real_cell("oak_cell.yaml", OAK_CAMERAS))
    monkeypatch.setitem(sys.modules, "depthai", None)  # as if not installed
    assert cli.main(["run", "--config", str(path), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["slidecal: cell.yaml: cameras.driver: is 'oak', which needs depthai (not "
                   "installed); install it with pip install 'slidecal[oak]'"]
    monkeypatch.setitem(sys.modules, "rtde_control", None)
    with pytest.raises(InputError, match=r"robot.driver: is 'ur', .*slidecal\[ur\]"):
        camera_rig(load_config(path))
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize(
    ("cameras", "message"),
    [
        ({**OAK_CAMERAS, "list": [{"name": "left", "width": 1280, "height": 800,
                                   "socket": "CAM_B", "exposure": 3}]},
         r"cameras.list\[0\].exposure: unknown key"),
        ({**OAK_CAMERAS, "list": [{"name": "left", "width": 1280, "height": 800,
                                   "socket": "LEFT"}]},
         r"cameras.list\[0\].socket: is 'LEFT'; use CAM_A"),
        ({**OAK_CAMERAS, "resize": "squash"}, "cameras.resize: is 'squash'; use one of stretch"),
        ({"driver": "uvc", "list": [{"name": "c", "width": 640, "height": 480}]},
         r"cameras.list\[0\].source: is missing"),
        ({"driver": "uvc", "list": [{"name": "a", "width": 640, "height": 480, "source": 0},
                                    {"name": "b", "width": 640, "height": 480, "source": 1}]},
         "cameras.list: holds 2 cameras; a uvc cell has one"),
    ],
)
def test_camera_fields_are_checked(tmp_path, monkeypatch, cameras, message):
    monkeypatch.setitem(sys.modules, "depthai", fake_depthai.make_fake_depthai(
        fake_depthai.World()))
    path = write_cell(tmp_path, real_cell("oak_cell.yaml", cameras))
    with pytest.raises(InputError, match=message):
        camera_rig(load_config(path))


@pytest.mark.slow
def test_an_oak_lost_mid_run_aborts_the_session_and_keeps_the_frames(tmp_path, oak_device,
                                                                     monkeypatch, capsys):
    """Issue 10 item 8 through the run: the queues close at the third capture; the run stops
    the robot, keeps the two frames, records the fault, exits with the hardware code and the
    pipeline is stopped. (The fake streams flat frames: no board is seen, which is not what
    this is about; ``--retries 0``: without it the routine reconnects the camera and goes on,
    which the unattended tests cover.)"""
    world, sim = oak_device
    robot = SimulatedCell.from_config(sim, seed=0).robot
    use_simulated_robot(monkeypatch, SimpleNamespace(robot=robot))
    settles = []

    def wait_settled(settle_s):
        settles.append(settle_s)
        if len(settles) == 3:
            world.lose_device()

    monkeypatch.setattr(robot, "wait_settled", wait_settled)
    path = write_cell(tmp_path, real_cell("oak_cell.yaml", OAK_CAMERAS))
    sdir = tmp_path / "s"
    code = cli.main(["run", "--config", str(path), "--out", str(sdir), "--quiet",
                     "--no-recording", "--retries", "0"])
    err = capsys.readouterr().err
    assert code == 3, err
    assert f"OAK device {world.device_id} lost during capture" in err
    assert "the 2 frames captured before it" in err
    session = yaml.safe_load((sdir / "session.yaml").read_text())
    assert session["status"] == "aborted" and len(session["frames"]) == 2
    assert session["events"][0]["kind"] == "fault"
    assert not world.pipelines[0].isRunning() and ("stop",) in world.calls


def test_an_incomplete_rig_result_is_compared_where_it_can_be(tmp_path, oak_device):
    """A result without the colour camera's translation (no tilts seen by it): no depthai
    export (it needs every link), said in the summary; the other cameras still compared."""
    from slidecal.drivers.oak import OakRig
    from slidecal.routines.devices import device_calibration_outputs, record_devices

    _, sim = oak_device
    rig = OakRig(focus={"rgb": 130})
    rig.open()
    sdir = tmp_path / "s"
    devices = record_devices(rig, sdir, 0.5)
    rig.close()
    SessionWriter(sdir, sim.target, rig.specs, extra=devices).finish()
    r = truth_result(sim)
    rot_only = TransformEstimate("T_rgb_left", r.rig["T_rgb_left"].R, None)
    r = CalibrationResult(**{**r.__dict__, "rig": {**r.rig, "T_rgb_left": rot_only}})
    paths, text = device_calibration_outputs(r, sdir, sdir / "export")
    assert paths == []
    assert "note: no depthai calibration export" in text and "T_rgb_left" in text
    line = next(x for x in text.splitlines() if x.startswith("device factory"))
    assert "left 0.00 rms" in line and "right 0.00 rms" in line and "rgb" not in line



def test_flash_refuses_a_session_without_an_oak(tmp_path, capsys):
    sim = load_packaged_cell("default_cell.yaml")
    SessionWriter(tmp_path / "s", sim.target, sim.cameras).finish()
    assert cli.main(["flash", str(tmp_path / "s"), "--write"]) == 2
    assert "was not recorded with an OAK" in capsys.readouterr().err

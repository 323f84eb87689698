"""UvcCamera: for real on a video file written by cv2.VideoWriter, and against a fake
cv2.VideoCapture for what a file cannot show (size fallback, exposure, unplugging)."""

from __future__ import annotations

import inspect
import re

import cv2
import numpy as np
import pytest

from slidecal.drivers.base import CameraRig
from slidecal.drivers.uvc import UvcCamera
from slidecal.solver.errors import HardwareFault, InputError


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "clip.avi"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (160, 120))
    assert w.isOpened()
    for i in range(12):
        w.write(np.full((120, 160, 3), 20 * i, np.uint8))  # frame i is uniformly 20 i
    w.release()
    return path


def test_real_video_file_drops_buffered_frames(video):
    cam = UvcCamera(video, "cam", 160, 120, drop_frames=2)
    assert isinstance(cam, CameraRig)
    cam.open()
    values = []
    for _ in range(3):
        img = cam.capture()["cam"]
        assert img.shape == (120, 160, 3) and img.dtype == np.uint8
        values.append(float(img.mean()))
    # Each capture drops 2 frames and keeps the third: frames 2, 5, 8. MJPEG is lossy: +-3.
    np.testing.assert_allclose(values, [40.0, 100.0, 160.0], atol=3.0)
    cam.capture()  # frame 11, the last one
    with pytest.raises(HardwareFault, match="no frame"):
        cam.capture()
    cam.close()
    cam.close()


def test_real_video_file_size_mismatch_refused(video):
    with pytest.raises(HardwareFault, match="160x120 instead of 320x240"):
        UvcCamera(video, "cam", 320, 240).open()
    with pytest.raises(HardwareFault, match="cannot open"):
        UvcCamera(video.with_name("missing.avi"), "cam", 160, 120).open()


class FakeCapture:
    """cv2.VideoCapture's interface: set/get of properties, grab/retrieve, isOpened/release.

    Like V4L2: a property the camera lacks cannot be set and reads -1; ``autofocus`` is
    "off-able", "stuck" (reads 1 whatever is set) or "absent"; exposure snaps to steps of
    ``exposure_step``. Like OpenCV's V4L2 backend (``cap_v4l.cpp``): with ``normalized`` (the
    environment's ``OPENCV_VIDEOIO_V4L_RANGE_NORMALIZED``) ``CAP_PROP_AUTO_EXPOSURE`` is mapped
    from [0, 1) onto V4L2's menu 0..4 (1 is then no valid entry and is refused), until
    ``CAP_PROP_MODE`` is set to 0 (raw ranges; it then reads 0)."""

    instances: list[FakeCapture] = []
    sizes = [(640, 480), (1280, 720)]
    exposure_supported = True
    exposure_step = 1.0
    autofocus = "off-able"
    white_balance = "absent"  # "off-able", "stuck" (stays on) or "absent" (a grey camera)
    frames_left = 100
    normalized = False

    def __init__(self, source, apiPreference=cv2.CAP_ANY):  # noqa: N803 - OpenCV's name
        self.source, self.api = source, apiPreference
        self.props = {
            cv2.CAP_PROP_FRAME_WIDTH: 640.0,
            cv2.CAP_PROP_FRAME_HEIGHT: 480.0,
            cv2.CAP_PROP_AUTOFOCUS: 1.0,
            cv2.CAP_PROP_AUTO_EXPOSURE: 3.0,
            cv2.CAP_PROP_EXPOSURE: 166.0,
            cv2.CAP_PROP_FPS: 30.0,
        }
        if self.white_balance != "absent":
            self.props[cv2.CAP_PROP_AUTO_WB] = 1.0
            self.props[cv2.CAP_PROP_WB_TEMPERATURE] = 4600.0
        self.sets = []
        self.grabs = 0
        self.released = False
        FakeCapture.instances.append(self)

    def isOpened(self):
        return self.source != 99

    def getBackendName(self):
        return "V4L2" if self.api == cv2.CAP_V4L2 else "FFMPEG"

    def set(self, prop, value):
        self.sets.append((prop, value))
        if prop == cv2.CAP_PROP_MODE:
            self.normalized = bool(round(value))
            return True
        if prop == cv2.CAP_PROP_AUTO_EXPOSURE and self.normalized:
            value = round(value * 4)  # Range(0, 4)
            if value not in (1, 3):  # V4L2's manual and aperture-priority entries
                return False
        if prop in (cv2.CAP_PROP_AUTO_EXPOSURE, cv2.CAP_PROP_EXPOSURE):
            if not self.exposure_supported:
                return False
            if prop == cv2.CAP_PROP_EXPOSURE:
                value = round(value / self.exposure_step) * self.exposure_step
        if prop in (cv2.CAP_PROP_AUTO_WB, cv2.CAP_PROP_WB_TEMPERATURE):
            if self.white_balance == "absent":
                return False
            if self.white_balance == "stuck" and prop == cv2.CAP_PROP_AUTO_WB:
                return True
        if prop in (cv2.CAP_PROP_AUTOFOCUS, cv2.CAP_PROP_FOCUS):
            if self.autofocus == "absent":
                self.props.pop(cv2.CAP_PROP_AUTOFOCUS, None)
                return False
            if self.autofocus == "stuck" and prop == cv2.CAP_PROP_AUTOFOCUS:
                return True  # the driver says yes and does nothing
        self.props[prop] = float(value)
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:  # snap to a supported size, as drivers do
            want = (self.props[cv2.CAP_PROP_FRAME_WIDTH], value)
            if want not in self.sizes:
                self.props[cv2.CAP_PROP_FRAME_WIDTH], self.props[prop] = self.sizes[0]
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_MODE:
            return self.props.get(cv2.CAP_PROP_FOURCC, 0.0) if self.normalized else 0.0
        if prop == cv2.CAP_PROP_AUTO_EXPOSURE and self.normalized:
            return self.props[prop] / 4
        return self.props.get(prop, -1.0)

    def grab(self):
        if FakeCapture.frames_left <= 0:
            return False
        FakeCapture.frames_left -= 1
        self.grabs += 1
        return True

    def retrieve(self):
        w, h = int(self.props[cv2.CAP_PROP_FRAME_WIDTH]), int(self.props[cv2.CAP_PROP_FRAME_HEIGHT])
        return True, np.full((h, w, 3), self.grabs, np.uint8)

    def release(self):
        self.released = True


def test_fake_capture_has_only_what_cv2_videocapture_has():
    mine = [k for k, v in vars(FakeCapture).items() if not k.startswith("_") and callable(v)]
    assert set(mine) <= set(dir(cv2.VideoCapture)), set(mine) - set(dir(cv2.VideoCapture))
    for name in mine:  # the required arguments, from OpenCV's "set(propId, value) -> retval"
        doc = getattr(cv2.VideoCapture, name).__doc__.strip().splitlines()[0]
        args = re.match(rf"{name}\((.*?)\) ->", doc).group(1).split("[")[0]  # [optional]
        required = [a for a in args.split(", ") if a.strip(" ,")]
        params = list(inspect.signature(vars(FakeCapture)[name]).parameters)[1:]
        assert len(params) == len(required), (name, params, required)


@pytest.fixture
def fake(monkeypatch):
    FakeCapture.instances = []
    FakeCapture.exposure_supported = True
    FakeCapture.exposure_step = 1.0
    FakeCapture.autofocus = "off-able"
    FakeCapture.frames_left = 100
    FakeCapture.normalized = False
    FakeCapture.white_balance = "absent"
    monkeypatch.setattr(cv2, "VideoCapture", FakeCapture)
    return FakeCapture


def test_fake_sets_format_size_exposure_and_drops_frames(fake):
    cam = UvcCamera(0, "wrist", 1280, 720, fourcc="MJPG", exposure=150, drop_frames=4)
    cam.open()
    cap = fake.instances[0]
    assert (cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*"MJPG")) in cap.sets
    assert (cv2.CAP_PROP_AUTO_EXPOSURE, 1) in cap.sets
    assert (cv2.CAP_PROP_EXPOSURE, 150.0) in cap.sets
    assert cam.messages == []
    img = cam.capture()["wrist"]
    assert img.shape == (720, 1280, 3) and int(img[0, 0, 0]) == 5  # 4 dropped, the 5th kept
    cam.close()
    assert cap.released


def test_autofocus_is_switched_off_and_read_back(fake):
    cam = UvcCamera(0, "c", 640, 480, focus=40, fps=15)
    cam.open()
    cap = fake.instances[0]
    assert (cv2.CAP_PROP_AUTOFOCUS, 0.0) in cap.sets and cap.get(cv2.CAP_PROP_AUTOFOCUS) == 0
    assert cap.get(cv2.CAP_PROP_FOCUS) == 40 and cap.get(cv2.CAP_PROP_FPS) == 15
    settings = cam.capabilities()["settings"]
    assert settings["autofocus"] == {"requested": 0.0, "read_back": 0.0, "accepted": True}
    assert settings["focus"]["accepted"] and settings["fps"]["read_back"] == 15
    assert cam.capabilities()["backend"] == "V4L2" and cam.messages == []
    cam.close()


def test_a_camera_that_keeps_autofocus_on_is_refused(fake):
    fake.autofocus = "stuck"
    with pytest.raises(HardwareFault, match="keeps autofocus on"):
        UvcCamera(0, "c", 640, 480).open()
    assert fake.instances[0].released
    fake.autofocus = "absent"
    cam = UvcCamera(0, "c", 640, 480)
    cam.open()
    assert cam.messages == ["camera c: no autofocus control (fixed focus)"]


def test_settings_the_camera_ignores_are_reported(fake):
    fake.exposure_step = 39.0  # 150 reads back as 156
    cam = UvcCamera(0, "c", 640, 480, exposure=150)
    # issue 36 item 7: a requested exposure that did not lock is refused, not noted
    with pytest.raises(HardwareFault, match="manual exposure 150 not taken") as e:
        cam.open()
    assert cam.settings["exposure"] == {"requested": 150.0, "read_back": 156.0, "accepted": False}
    assert "exposure 156" in str(e.value) and fake.instances[0].released


def test_fake_refuses_size_fallback_and_reports_missing_exposure(fake):
    with pytest.raises(HardwareFault, match="640x480 instead of 1920x1080"):
        UvcCamera(0, "c", 1920, 1080).open()
    assert fake.instances[0].released
    fake.exposure_supported = False
    cam = UvcCamera(0, "c", 640, 480, exposure=100)
    with pytest.raises(HardwareFault, match="manual exposure 100 not taken"):
        cam.open()


def test_fake_unplugged_and_not_open(fake):
    with pytest.raises(HardwareFault, match="cannot open"):
        UvcCamera(99, "c", 640, 480).open()
    cam = UvcCamera(0, "c", 640, 480)
    with pytest.raises(HardwareFault, match="not open"):
        cam.capture()
    cam.open()
    fake.frames_left = 2
    with pytest.raises(HardwareFault, match="no frame"):
        cam.capture()


def test_bad_arguments():
    with pytest.raises(InputError):
        UvcCamera(0, "c", 0, 480)
    with pytest.raises(InputError, match="fourcc"):
        UvcCamera(0, "c", 640, 480, fourcc="MJPEG")


def test_auto_exposure_is_locked_where_it_settled_and_read_back(fake):
    """Without a manual exposure the camera's auto exposure runs ``settle_frames`` frames and is
    then switched off at the exposure it reached (the old driver left it running)."""
    cam = UvcCamera(0, "c", 640, 480, settle_frames=12)
    cam.open()
    cap = fake.instances[0]
    assert cap.grabs == 12  # settled before locking
    assert (cv2.CAP_PROP_AUTO_EXPOSURE, 1) in cap.sets
    assert (cv2.CAP_PROP_EXPOSURE, 166.0) in cap.sets
    settings = cam.capabilities()["settings"]
    assert settings["auto_exposure"]["read_back"] == 1.0
    assert settings["exposure"] == {"requested": 166.0, "read_back": 166.0, "accepted": True}
    assert settings["auto_white_balance"]["read_back"] == -1.0  # a grey camera: no control
    assert cam.messages == []


def test_auto_white_balance_is_locked_where_it_settled(fake):
    fake.white_balance = "off-able"
    cam = UvcCamera(0, "c", 640, 480, exposure=100, settle_frames=6)
    cam.open()
    cap = fake.instances[0]
    assert cap.grabs == 6 and cap.get(cv2.CAP_PROP_AUTO_WB) == 0.0
    settings = cam.capabilities()["settings"]
    assert settings["white_balance_k"] == {"requested": 4600.0, "read_back": 4600.0,
                                           "accepted": True}
    assert cam.messages == []
    fake.white_balance = "stuck"
    cam = UvcCamera(0, "c", 640, 480, exposure=100)
    cam.open()
    assert "auto white balance could not be locked" in cam.messages[0]


def test_a_camera_without_exposure_control_is_reported(fake):
    fake.exposure_supported = False
    cam = UvcCamera(0, "c", 640, 480, settle_frames=0)
    cam.open()
    assert "locking the exposure at 166 not taken" in cam.messages[0]


def test_a_camera_is_opened_with_v4l2_in_raw_ranges(fake, monkeypatch):
    """Issue 36 item 7: ``CAP_PROP_AUTO_EXPOSURE = 1`` means manual only in OpenCV's V4L2
    backend with raw ranges. A camera on Linux is opened with ``CAP_V4L2`` and switched to raw
    ranges before any control, so a normalising environment cannot turn the lock into a no-op."""
    monkeypatch.setattr("sys.platform", "linux")
    fake.normalized = True  # OPENCV_VIDEOIO_V4L_RANGE_NORMALIZED=1
    cam = UvcCamera(0, "c", 640, 480, exposure=150)
    cam.open()
    cap = fake.instances[0]
    assert cap.api == cv2.CAP_V4L2 and cam.capabilities()["backend"] == "V4L2"
    assert cap.sets[0] == (cv2.CAP_PROP_MODE, 0.0)
    assert cam.settings["raw_ranges"]["accepted"]
    assert cap.get(cv2.CAP_PROP_AUTO_EXPOSURE) == 1.0 and cam.messages == []


def test_the_real_opencv_takes_the_v4l2_backend_without_a_device():
    """The real cv2.VideoCapture with CAP_V4L2 and no such device: not opened, said in one
    line (the real video-file tests above open through the default backend)."""
    with pytest.raises(HardwareFault, match="cannot open 63"):
        UvcCamera(63, "c", 640, 480).open()

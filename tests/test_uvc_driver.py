"""UvcCamera: for real on a video file written by cv2.VideoWriter, and against a fake
cv2.VideoCapture for what a file cannot show (size fallback, exposure, unplugging)."""

from __future__ import annotations

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
    """cv2.VideoCapture's interface: set/get of properties, grab/retrieve, isOpened/release."""

    instances: list[FakeCapture] = []
    sizes = [(640, 480), (1280, 720)]
    exposure_supported = True
    frames_left = 100

    def __init__(self, source):
        self.source = source
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 640.0, cv2.CAP_PROP_FRAME_HEIGHT: 480.0}
        self.sets = []
        self.grabs = 0
        self.released = False
        FakeCapture.instances.append(self)

    def isOpened(self):
        return self.source != 99

    def set(self, prop, value):
        self.sets.append((prop, value))
        if prop in (cv2.CAP_PROP_AUTO_EXPOSURE, cv2.CAP_PROP_EXPOSURE):
            return self.exposure_supported
        self.props[prop] = float(value)
        if prop == cv2.CAP_PROP_FRAME_HEIGHT:  # snap to a supported size, as drivers do
            want = (self.props[cv2.CAP_PROP_FRAME_WIDTH], value)
            if want not in self.sizes:
                self.props[cv2.CAP_PROP_FRAME_WIDTH], self.props[prop] = self.sizes[0]
        return True

    def get(self, prop):
        return self.props.get(prop, 0.0)

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


@pytest.fixture
def fake(monkeypatch):
    FakeCapture.instances = []
    FakeCapture.exposure_supported = True
    FakeCapture.frames_left = 100
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


def test_fake_refuses_size_fallback_and_reports_missing_exposure(fake):
    with pytest.raises(HardwareFault, match="640x480 instead of 1920x1080"):
        UvcCamera(0, "c", 1920, 1080).open()
    assert fake.instances[0].released
    fake.exposure_supported = False
    cam = UvcCamera(0, "c", 640, 480, exposure=100)
    cam.open()
    assert "manual exposure not supported" in cam.messages[0]


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

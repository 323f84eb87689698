"""A rerun recording of a calibration run, ``SESSION_DIR/recording.rrd`` (rerun-sdk 0.41; the
only module that imports rerun). Its entity tree and timelines: docs/DRIVERS.md."""

from __future__ import annotations

import shutil
from collections.abc import Mapping, Sequence
from contextlib import suppress
from pathlib import Path

import numpy as np
import rerun as rr

from slidecal.solver.camera import project
from slidecal.solver.drift import T_cam_board, hand_eye_T
from slidecal.solver.errors import InputError
from slidecal.solver.problem import CalibrationProblem, CameraSpec, Detection, Target
from slidecal.solver.result import CalibrationResult

RECORDING_FILE = "recording.rrd"
_AXES = np.eye(3) * 0.05
_AXIS_COLOURS = [[255, 0, 0], [0, 255, 0], [0, 0, 255]]


class RerunLog:
    """Log one run (the entity tree: docs/DRIVERS.md).

    ``path``: the ``.rrd`` file (None: none). ``cameras``: the rig's cameras. ``target``: the board.
    ``mount``: ``eye_in_hand`` | ``eye_to_hand``. ``T_hand_eye_approx``, ``T_target_approx``: (4, 4)
    metres, shown while recording. ``spawn``: also stream to a viewer.
    """

    def __init__(
        self,
        path: str | Path | None,
        cameras: Sequence[CameraSpec],
        target: Target,
        mount: str,
        T_hand_eye_approx: np.ndarray,
        T_target_approx: np.ndarray,
        spawn: bool = False,
    ) -> None:
        self.rec = rr.RecordingStream("slidecal")
        self.path = Path(path) if path is not None else None
        if spawn:
            if shutil.which("rerun") is None:  # asked first: rerun itself would log to stderr
                raise RuntimeError("no rerun viewer executable (`rerun`) on PATH")
            self.rec.spawn()
        if self.path is not None:
            self.rec.save(self.path)
        self.cameras = {c.name: c for c in cameras}
        self.target = target
        self.mount = mount
        self._path_points: list[np.ndarray] = []
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log(
            "world/base", rr.Arrows3D(vectors=_AXES * 2, colors=_AXIS_COLOURS), static=True
        )
        self._log_board(T_target_approx, static=True)
        for name, spec in self.cameras.items():  # a stand-in pinhole (70 deg) until an estimate
            w, h, f = spec.width, spec.height, 0.7 * max(spec.width, spec.height)
            K = np.array([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0, 0, 1]])
            self._log_camera(name, spec, K, T_hand_eye_approx, static=True)

    def _cam_path(self, name: str) -> str:
        return f"world/tool/{name}" if self.mount == "eye_in_hand" else f"world/{name}"

    def _log_board(self, T_target: np.ndarray, static: bool = False) -> None:
        p = "world/board" if self.mount == "eye_in_hand" else "world/tool/board"
        self.rec.log(
            p, rr.Transform3D(translation=T_target[:3, 3], mat3x3=T_target[:3, :3]), static=static
        )
        self.rec.log(
            f"{p}/corners",
            rr.Points3D(self.target.points_m, radii=0.002, colors=[200, 200, 0]),
            static=static,
        )

    def _log_camera(
        self,
        name: str,
        spec: CameraSpec,
        K: np.ndarray,
        T_parent_cam: np.ndarray,
        static: bool = False,
    ) -> None:
        p = self._cam_path(name)
        self.rec.log(
            p,
            rr.Transform3D(translation=T_parent_cam[:3, 3], mat3x3=T_parent_cam[:3, :3]),
            static=static,
        )
        self.rec.log(
            p,
            rr.Pinhole(
                image_from_camera=K,
                resolution=[spec.width, spec.height],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.1,
            ),
            static=static,
        )

    def _time(self, frame: int, robot_time_s: float | None) -> None:
        self.rec.set_time("capture", sequence=int(frame))
        if robot_time_s is not None:
            self.rec.set_time("robot_time", duration=float(robot_time_s))

    def frame(
        self,
        frame: int,
        T_base_tool: np.ndarray | None,
        images: Mapping[str, np.ndarray],
        detections: Mapping[str, Detection],
        robot_time_s: float | None = None,
    ) -> None:
        """One capture: the measured tool pose (4, 4), metres; images; detections (pixels)."""
        self._time(frame, robot_time_s)
        if T_base_tool is not None:
            self.rec.log(
                "world/tool",
                rr.Transform3D(translation=T_base_tool[:3, 3], mat3x3=T_base_tool[:3, :3]),
            )
            self.rec.log("world/tool/axes", rr.Arrows3D(vectors=_AXES, colors=_AXIS_COLOURS))
            self._path_points.append(T_base_tool[:3, 3].copy())
            self.rec.log("world/tool_path", rr.LineStrips3D([np.array(self._path_points)]))
        for name, img in images.items():
            self.rec.log(f"{self._cam_path(name)}/image", rr.Image(img).compress(jpeg_quality=80))
        for name, det in detections.items():
            self.rec.log(
                f"{self._cam_path(name)}/image/detections",
                rr.Points2D(det.px, radii=2.0, colors=[0, 255, 0]),
            )

    def event(self, text: str, level: str = "INFO") -> None:
        """A line in ``log`` (``INFO``, ``WARN``, ``ERROR``)."""
        self.rec.log("log", rr.TextLog(text, level=level))

    def final(self, problem: CalibrationProblem, result: CalibrationResult, summary: str) -> None:
        """The estimate: cameras and board at their estimated poses, reprojections, residuals
        per frame, and the summary (estimate with its uncertainty) as a ``TextLog``."""
        Tt = result.T_target.T if result.T_target is not None else None
        if Tt is not None:
            self._log_board(Tt, static=True)
        X = {}  # each camera's hand-eye, where the solve determined it
        for name, est in result.cameras.items():
            with suppress(InputError):
                X[name] = hand_eye_T(result, name)
                self._log_camera(name, self.cameras[name], est.K, X[name], static=True)
        for fr in problem.frames:
            self._time(fr.id, None)
            for name, det in fr.detections.items():
                rms = result.residuals_px.get((fr.id, name))
                if rms is not None:
                    self.rec.log(f"residuals/{name}", rr.Scalars(float(rms)))
                est = result.cameras.get(name)
                if est is None or Tt is None or fr.T_base_tool is None or name not in X:
                    continue
                if len(det.ids) == 0:
                    continue
                T_cb = T_cam_board(problem.mount, X[name], fr.T_base_tool, Tt)
                P = problem.target.points_m[det.ids] @ T_cb[:3, :3].T + T_cb[:3, 3]
                px = project(est.K, est.distortion, P)
                self.rec.log(
                    f"{self._cam_path(name)}/image/reprojections",
                    rr.Points2D(px, radii=1.5, colors=[255, 0, 255]),
                )
        self.rec.log("log", rr.TextLog(summary, level="INFO"))

    def close(self) -> Path | None:
        """Flush and finish the recording; return its path."""
        self.rec.flush()
        self.rec.disconnect()
        return self.path

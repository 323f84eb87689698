"""Exports of an accepted calibration for other tools (``export/``, never for a rejected result)
and the result header; what each file holds and where a lens model cannot go: docs/UNATTENDED.md,
"Exports and the result header". A failed export does not stop the others:
:func:`write_all_exports` returns the failures as one-line messages."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from slidecal import mocks
from slidecal.drivers.ur_pose import rpy_deg
from slidecal.routines import __version__
from slidecal.routines.ops.report import uncertainty_map
from slidecal.routines.results_io import hand_eye_transforms
from slidecal.routines.schema import dump_yaml, plain, write_atomic, write_yaml
from slidecal.solver.camera import distortion_model
from slidecal.solver.errors import SlidecalError
from slidecal.solver.geometry import rvec_from_R
from slidecal.solver.result import CalibrationResult, CameraEstimate

CAMCHAIN_FILE = "camchain.yaml"
MRCAL_SUFFIX = ".cameramodel"
HAND_EYE_FILE = "hand_eye.yaml"
DEPTHAI_FILE = "depthai_calibration.json"

#: mrcal's name of each lens model (a k3 not estimated, 0, is mrcal's OPENCV4); mrcal has no
#: Kannala-Brandt model
MRCAL_MODELS = {"opencv5": "LENSMODEL_OPENCV5", "rational": "LENSMODEL_OPENCV8"}
#: ROS camera_info's name of each lens model (image_pipeline's camera_calibration_parsers)
ROS_MODELS = {"opencv5": "plumb_bob", "rational": "rational_polynomial", "fisheye": "equidistant"}
#: Kalibr's name of each lens model it has (radtan: opencv5 without k3)
KALIBR_MODELS = {"opencv5": "radtan", "fisheye": "equidistant"}
#: ``valid_intrinsics_region``: where the one-sigma projection uncertainty is below this
#: (docs/ERROR_MODEL.md Sec. 4)
VALID_REGION_PX = 1.0


def result_header(cell_path: str | Path | None, cell_name: str | None = None) -> dict[str, Any]:
    """``{slidecal_version, created_utc, cell, cell_sha256}``; without a cell file the packaged cell
    ``cell_name`` is hashed."""
    cell = Path(cell_path) if cell_path is not None else None
    if cell is None and cell_name:
        cell = Path(mocks.__file__).parent / str(cell_name)  # a cell packaged with the simulator
    try:
        digest = hashlib.sha256(cell.read_bytes()).hexdigest() if cell is not None else None
    except OSError:  # no such file (a packaged cell's name that is not one), a directory
        digest = None
    return {
        "slidecal_version": __version__,
        "created_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "cell": str(cell_name or (Path(cell_path).name if cell_path else "unknown")),
        "cell_sha256": digest,
    }


def write_opencv_yaml(camera: CameraEstimate, path: Path) -> None:
    """OpenCV ``FileStorage`` YAML of one camera, as OpenCV's calibration sample writes it
    (``camera_matrix`` 3x3, ``distortion_coefficients`` 1x5 or 1x8 for ``cv2`` or 1x4 for
    ``cv2.fisheye`` with ``fisheye_model: 1``, ``avg_reprojection_error`` px)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        fs.write("camera_name", camera.name)
        fs.write("camera_matrix", np.asarray(camera.K, dtype=np.float64))
        d = np.asarray(camera.distortion, dtype=np.float64).reshape(1, -1)
        fs.write("distortion_coefficients", d)
        if distortion_model(d) == "fisheye":
            fs.write("fisheye_model", 1)
        fs.write("avg_reprojection_error", float(camera.reproj_rms_px))
    finally:
        fs.release()


def camera_info_dict(camera: CameraEstimate) -> dict[str, Any]:
    """The ROS ``camera_info`` mapping of one camera (monocular: identity rectification, projection
    ``[K | 0]``; ``plumb_bob`` is OpenCV's k1 k2 p1 p2 k3, ``rational_polynomial`` its eight
    coefficients, ``equidistant`` its fisheye's four)."""
    K, d = np.asarray(camera.K, dtype=float), np.asarray(camera.distortion, dtype=float).ravel()
    P = np.hstack([K, np.zeros((3, 1))])
    return {
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "camera_name": camera.name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": plain(K.reshape(-1))},
        "distortion_model": ROS_MODELS[distortion_model(d)],
        "distortion_coefficients": {"rows": 1, "cols": len(d), "data": plain(d)},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": plain(np.eye(3).reshape(-1))},
        "projection_matrix": {"rows": 3, "cols": 4, "data": plain(P.reshape(-1))},
    }


def _ordered_cameras(result: CalibrationResult) -> list[str]:
    ref = result.reference_camera or next(iter(result.cameras))
    return [ref] + [n for n in result.cameras if n != ref]


def _T_cam_ref(result: CalibrationResult, name: str, ref: str) -> np.ndarray | None:
    if name == ref:
        return np.eye(4)
    t = result.rig.get(f"T_{name}_{ref}")
    return t.T if t is not None else None


def _no_skew(result: CalibrationResult, model: str) -> None:
    """Raise ``ValueError`` (one line) when a camera's skew is not zero (``model`` has none)."""
    for name, c in result.cameras.items():
        K = np.asarray(c.K, dtype=float)
        if abs(K[0, 1]) > 1e-9 * abs(K[0, 0]):
            raise ValueError(
                f"camera {name} has a skew of {K[0, 1]:.4g} px, which {model} cannot hold; "
                "solve without the skew option (options: {skew: false}) for this export"
            )


def _lens(
    name: str, c: CameraEstimate, models: Mapping[str, str], lacks: str, fix: str
) -> tuple[str, np.ndarray]:
    """Camera ``name``'s lens model and coefficients; ``ValueError`` (one line) when a format's
    ``models`` have no such lens (``lacks``: whose; ``fix``: the options that solve for one)."""
    d = np.asarray(c.distortion, dtype=float).reshape(-1)
    model = distortion_model(d)
    if model not in models:
        raise ValueError(
            f"camera {name} has the {model} lens model, which {lacks}; solve with options: "
            f"{fix} for this export"
        )
    return model, d


def camchain_dict(result: CalibrationResult) -> dict:
    """Kalibr's ``camchain.yaml`` mapping (cam0 is the reference camera). ``ValueError`` when a
    camera has a skew, a k3 (Kalibr's pinhole-radtan model has neither) or the rational model."""
    _no_skew(result, "Kalibr's pinhole model")
    for name, c in result.cameras.items():
        model, d = _lens(name, c, KALIBR_MODELS, "Kalibr does not have",
                         "{distortion_model: opencv5} (k3 fixed) or fisheye")  # fmt: skip
        k3 = float(d[4]) if model == "opencv5" else 0.0
        if k3 != 0.0:
            raise ValueError(
                f"camera {name} has k3 = {k3:.4g}, which Kalibr's radtan model cannot hold (it "
                "would be dropped); solve with k3 fixed (options: {distortion: [true, true, true, "
                "true, false]}) for this export"
            )
    out: dict[str, Any] = {}
    names = _ordered_cameras(result)
    ref = names[0]
    for i, n in enumerate(names):
        c = result.cameras[n]
        K = np.asarray(c.K, dtype=float)
        d = np.asarray(c.distortion, dtype=float).reshape(-1)
        entry: dict[str, Any] = {
            "camera_model": "pinhole",
            "intrinsics": plain([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]),
            "distortion_model": KALIBR_MODELS[distortion_model(d)],
            "distortion_coeffs": plain(d[:4]),
            "resolution": [int(c.width), int(c.height)],
            "rostopic": f"/{n}/image_raw",
            "cam_overlaps": [j for j in range(len(names)) if j != i],
        }
        if i > 0:
            Ta, Tb = _T_cam_ref(result, n, ref), _T_cam_ref(result, names[i - 1], ref)
            if Ta is not None and Tb is not None:
                entry["T_cn_cnm1"] = plain(Ta @ np.linalg.inv(Tb))
        out[f"cam{i}"] = entry
    return out


def _numbers(values: Any) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def mrcal_cameramodel(
    result: CalibrationResult, name: str, header: Mapping[str, Any] | None = None
) -> str:
    """mrcal's ``.cameramodel`` text (a Python ``dict`` literal) of camera ``name`` (what it holds:
    docs/UNATTENDED.md), the lens model before ``intrinsics`` (mrcal's C reader wants that order).
    ``ValueError`` when the camera has a skew, a fisheye lens or its rig transform is missing."""
    _no_skew(result, "mrcal's OpenCV lens models")
    c = result.cameras[name]
    model, dist = _lens(name, c, MRCAL_MODELS, "mrcal does not have (no Kannala-Brandt)",
                        "{distortion_model: rational}")  # fmt: skip
    lensmodel = MRCAL_MODELS[model]
    if model == "opencv5" and dist[4] == 0.0:
        lensmodel, dist = "LENSMODEL_OPENCV4", dist[:4]
    ref = _ordered_cameras(result)[0]
    T = _T_cam_ref(result, name, ref)
    if T is None:
        raise ValueError(f"the result holds no T_{name}_{ref}: camera {name} has no pose")
    K = np.asarray(c.K, dtype=float)
    intrinsics = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]
    rt = [*rvec_from_R(T[:3, :3]), *T[:3, 3]]
    region = _valid_region(result, name)
    lines = [f"# {k}: {v}" for k, v in (header or {}).items()]
    lines += [
        f"# camera {name} from slidecal; the reference camera is {ref}",
        "{",
        f"    'lensmodel': '{lensmodel}',",
        "    # fx, fy, cx, cy, then OpenCV's distortion coefficients in its order",
        f"    'intrinsics': {_numbers(intrinsics)},",
        f"    'rt_cam_ref': {_numbers(rt)},",
        f"    'extrinsics': {_numbers(rt)},",
        f"    'imagersize': [{int(c.width)}, {int(c.height)}],",
    ]
    if region is not None:
        lines += [
            f"    # the one-sigma projection uncertainty is below {VALID_REGION_PX} px inside",
            f"    'valid_intrinsics_region': [{', '.join(_numbers(p) for p in region)}],",
        ]
    return "\n".join([*lines, "}"]) + "\n"


def _valid_region(result: CalibrationResult, name: str) -> np.ndarray | None:
    """The closed contour (N, 2) px of the largest image region where camera ``name``'s one-sigma
    projection uncertainty is below :data:`VALID_REGION_PX`; None without a covariance or where
    it is nowhere below."""
    m = uncertainty_map(result, name)
    if m is None:
        return None
    contours = cv2.findContours(
        (m < VALID_REGION_PX).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
    )[0]
    if not contours or len(best := max(contours, key=cv2.contourArea)) < 3:
        return None
    c = result.cameras[name]
    xy = best.reshape(-1, 2) * [(c.width - 1) / (m.shape[1] - 1), (c.height - 1) / (m.shape[0] - 1)]
    return np.vstack([xy, xy[:1]])


def quat_xyzw(R: np.ndarray) -> list[float]:
    """The unit quaternion [x, y, z, w] (w >= 0) nearest to a 3x3 rotation matrix: the top
    eigenvector of Bar-Itzhack's symmetric 4x4 matrix."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(R, dtype=float)
    K = np.array(
        [
            [a - e - i, d + b, g + c, h - f],
            [d + b, e - a - i, h + f, c - g],
            [g + c, h + f, i - a - e, d - b],
            [h - f, c - g, d - b, a + e + i],
        ]
    )
    q = np.linalg.eigh(K)[1][:, -1]
    return [float(v) for v in (-q if q[3] < 0 else q)]


def hand_eye_dict(result: CalibrationResult, header: Mapping[str, Any] | None = None) -> dict:
    """``hand_eye.yaml``: every hand-eye transform in three forms; an undetermined translation is
    ``null``, without a matrix."""
    out: dict[str, Any] = {}
    if header:
        out["header"] = dict(header)
    out["conventions"] = (
        "T_a_b maps points in frame b into frame a; translation in metres unless named _mm; "
        "quaternion order x, y, z, w (Hamilton); rpy_deg: R = Rz(yaw) Ry(pitch) Rx(roll), the "
        "teach pendant's RPY"
    )
    for key, t in hand_eye_transforms(result).items():
        _, parent, child = key.split("_", 2)
        child = child if len(result.cameras) > 1 else next(iter(result.cameras))
        e: dict[str, Any] = {"parent_frame": parent, "child_frame": child}
        if t.R is None:
            e["rotation"] = None
            out[key] = e
            continue
        R = np.asarray(t.R, dtype=float)
        tm = None if t.t_m is None else np.asarray(t.t_m, dtype=float)
        e["matrix_4x4"] = plain(t.T) if tm is not None else None
        e["translation_m"] = plain(tm) if tm is not None else None
        e["quaternion_xyzw"] = quat_xyzw(R)
        e["ur_pendant"] = {
            "position_mm": plain(tm * 1000.0) if tm is not None else None,
            "rotation_vector_rad": plain(rvec_from_R(R)),
            "rpy_deg": rpy_deg(R),
        }
        e["std_rot_deg"] = t.std_rot_deg
        e["std_t_mm"] = t.std_t_mm if tm is not None else None
        out[key] = e
    return out


def write_all_exports(
    result: CalibrationResult,
    out_dir: str | Path,
    header: Mapping[str, Any] | None = None,
    oak_sockets: Mapping[str, Any] | None = None,
) -> tuple[list[Path], list[str]]:
    """Write every export into ``out_dir``; return (paths written, one line per export not
    written: a format that cannot hold the calibration, or an ``error:`` writing it)."""
    out = Path(out_dir)
    paths: list[Path] = []
    errors: list[str] = []

    def attempt(name: str, write) -> None:  # noqa: ANN001 - writes its file at the path given
        try:
            write(out / name)
            paths.append(out / name)
        except (SlidecalError, ValueError) as e:  # the format cannot hold this calibration
            errors.append(f"export {name} not written: {' '.join(str(e).split())}")
        except OSError as e:
            errors.append(f"error: export {name} failed: {' '.join(str(e).split())}")

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        return [], [f"error: export directory {out} cannot be created: {e.strerror or e}"]
    for name, cam in result.cameras.items():
        attempt(f"opencv_{name}.yaml", lambda p, c=cam: write_opencv_yaml(c, p))
        attempt(f"camera_info_{name}.yaml", lambda p, c=cam: write_yaml(p, camera_info_dict(c)))
    comment = "".join(f"# {k}: {v}\n" for k, v in (header or {}).items())
    attempt(CAMCHAIN_FILE, lambda p: write_atomic(p, comment + dump_yaml(camchain_dict(result))))
    for name in result.cameras:
        attempt(
            f"mrcal_{name}{MRCAL_SUFFIX}",
            lambda p, n=name: write_atomic(p, mrcal_cameramodel(result, n, header)),
        )
    if result.hand_eye is not None:
        attempt(HAND_EYE_FILE, lambda p: write_atomic(p, dump_yaml(hand_eye_dict(result, header))))
    if oak_sockets:
        from slidecal.drivers.oak import write_oak_calibration_json  # loaded for OAK rigs only

        attempt(DEPTHAI_FILE, lambda p: write_oak_calibration_json(result, p, dict(oak_sockets)))
    return paths, errors

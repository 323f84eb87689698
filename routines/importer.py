"""``slidecal import IMAGES_DIR POSES --config CELL --out SESSION_DIR``: a dataset recorded by
something else, a folder of images and the robot's poses in its controller's convention, as a
session; the convention found from the images (docs/FORMATS.md, "Recorded datasets") within the
record checks' limits (``solver/adequacy.py``).
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from slidecal.routines.config import load_config
from slidecal.routines.schema import load_yaml, read_text
from slidecal.routines.session import SessionWriter
from slidecal.solver.adequacy import (
    CONVENTION_MARGIN,
    MAX_PAIRING_LENGTH,
    MAX_PAIRING_ROTATION_DEG,
    MAX_ROBOT_TRANSLATION_MM,
    PAIRING_MIN_ROTATION_DEG,
    PAIRING_SAME_ORIENTATION_DEG,
    fixed_spread,
    moving_point,
)
from slidecal.solver.detect import (
    angles_between_deg,
    board_poses,
    detect,
    half_turn_symmetric,
    half_turn_T,
    half_turns,
)
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import T_from_Rt, inv_T, project_to_SO3
from slidecal.solver.problem import CalibrationProblem, CameraSpec, Detection, Frame

help = "turn a folder of images and a file of robot poses recorded elsewhere into a session"

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
SIDECAR_SUFFIXES = (".json", ".yaml", ".yml")
#: the keys a sidecar file's pose is looked for under, first found wins (or ``--pose-key``)
POSE_KEYS = ("pose", "pose_flange", "T_base_tool", "tool_pose", "robot_pose")
#: Euler orders real controllers use, as ``scipy``'s sequence of the angles in the file's order:
#: upper case about the turning axes (intrinsic), lower case about the fixed ones
EULER = {"Z-Y-X": "ZYX", "X-Y-Z fixed": "xyz", "X-Y-Z": "XYZ", "Z-Y-Z": "ZYZ"}
#: The rotation formats a row of 6, 7, 12 or 16 numbers may hold
READINGS = {
    6: (
        "rotation vector rad",
        "rotation vector deg",
        *(f"Euler {e} {u}" for e in EULER for u in ("deg", "rad")),
    ),
    7: ("quaternion w-first", "quaternion w-last"),
    12: ("3x4 matrix by rows",),
    16: ("4x4 matrix by rows", "4x4 matrix by columns"),
}
UNITS = {"m": 1.0, "mm": 1e-3}
DIRECTIONS = ("tool in base", "base in tool")
NUMBER = r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?"
MIN_MOVE_M = 0.005  # a shorter move's length is the images' noise (the pairing check's)


def natural_key(name: str) -> list[Any]:
    """Sort key putting ``2.jpg`` before ``10.jpg``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def conventions(n: int) -> list[str]:
    """Every reading of a row of ``n`` numbers, named as ``--convention`` takes them."""
    return [f"{u}, {r}, {d}" for r in READINGS[n] for u in UNITS for d in DIRECTIONS]


def pose_of(numbers: np.ndarray, unit: str, rotation: str, direction: str) -> np.ndarray:
    """``T_base_tool`` (4, 4), metres, of one record read in this convention."""
    v = np.asarray(numbers, dtype=float)
    if "matrix" in rotation:
        M = v.reshape(-1, 4) if "rows" in rotation else v.reshape(4, 4).T
        R, t = project_to_SO3(M[:3, :3]), M[:3, 3]
    else:
        t, a = v[:3], v[3:]
        deg = rotation.endswith("deg")
        if rotation.startswith("quaternion"):
            rot = Rotation.from_quat(a if "w-last" in rotation else np.roll(a, -1))
        elif rotation.startswith("rotation vector"):
            rot = Rotation.from_rotvec(a, degrees=deg)
        else:
            rot = Rotation.from_euler(EULER[rotation[6:-4]], a, degrees=deg)  # "Euler ... deg"
        R = rot.as_matrix()
    T = T_from_Rt(R, t * UNITS[unit])
    return T if direction == "tool in base" else inv_T(T)


def evidence(
    T_tool: np.ndarray, T_cam: Sequence[np.ndarray], mount: str, turn: np.ndarray | None = None
) -> dict[str, float]:
    """How poses ``T_tool`` (F, 4, 4) fit the images-alone ``T_cam`` (``T_cam_board``), with no
    hand-eye: the rms difference of the rotation angle between two frames (pairs turned by
    ``PAIRING_MIN_ROTATION_DEG`` or more), the median camera-to-robot length ratio of the pure
    moves (``MIN_MOVE_M`` or longer), and how far the board's pose in the base (eye-to-hand: on
    the tool) spreads through the poses with the best hand-eye (nan when the poses hold no
    rotation). ``turn``: a symmetric board's half turn (``half_turn_T``); each frame is first
    read the way round these poses' rotations tell (:func:`half_turns`)."""
    if turn is not None:
        turned = half_turns([T[:3, :3] for T in T_cam], list(T_tool[:, :3, :3]))[0]
        T_cam = [T @ turn if t else T for T, t in zip(T_cam, turned, strict=True)]
    iu = np.triu_indices(len(T_cam), 1)
    robot = angles_between_deg(T_tool[:, :3, :3])[iu]
    camera = angles_between_deg([T[:3, :3] for T in T_cam])[iu]
    t, p = T_tool[:, :3, 3], np.stack([moving_point(T, mount) for T in T_cam])
    move = np.linalg.norm(t[:, None] - t[None], axis=2)[iu]
    turned = np.maximum(robot, camera)
    errs = (camera - robot)[turned >= PAIRING_MIN_ROTATION_DEG]
    pure = (turned < PAIRING_SAME_ORIENTATION_DEG) & (move >= MIN_MOVE_M)
    ratios = np.linalg.norm(p[:, None] - p[None], axis=2)[iu][pure] / move[pure]
    spread = (float("nan"),) * 2
    if len(errs) >= 3:
        spread = fixed_spread(T_tool, list(T_cam), mount == "eye_in_hand")
    return {
        "rotation_rms_deg": float(np.sqrt(np.mean(np.square(errs)))) if len(errs) else np.nan,
        "rotated_pairs": len(errs),
        "move_ratio": float(np.median(ratios)) if len(ratios) else np.nan,
        "moved_pairs": len(ratios),
        "board_spread_deg": spread[0],
        "board_spread_mm": spread[1],
    }


def score(e: Mapping[str, float]) -> float:
    """The worst of the evidence's figures over its limit (<= 1: fits; nan parts are not asked;
    inf when nothing can be asked)."""
    parts = [
        e["rotation_rms_deg"] / MAX_PAIRING_ROTATION_DEG,
        abs(e["move_ratio"] - 1.0) / MAX_PAIRING_LENGTH,
        e["board_spread_deg"] / MAX_PAIRING_ROTATION_DEG,
        e["board_spread_mm"] / MAX_ROBOT_TRANSLATION_MM,
    ]
    parts = [p for p in parts if not np.isnan(p)]
    return max(parts) if parts else float("inf")


def describe(e: Mapping[str, float]) -> str:
    """The evidence in a few words."""
    out = []
    if e["rotated_pairs"]:
        out.append(f"rotations {e['rotation_rms_deg']:.2f} deg rms over {e['rotated_pairs']} pairs")
    if e["moved_pairs"]:
        out.append(f"moves x{e['move_ratio']:.3g} over {e['moved_pairs']} pairs")
    if not np.isnan(e["board_spread_deg"]):
        out.append(f"board spread {e['board_spread_deg']:.2f} deg, {e['board_spread_mm']:.1f} mm")
    return ", ".join(out) or "no pair of frames to compare"


def find_convention(
    records: Sequence[np.ndarray],
    T_cam: Sequence[np.ndarray],
    mount: str,
    forced: str | None = None,
    where: str = "poses",
    turn: np.ndarray | None = None,
) -> tuple[str, dict[str, float], list[tuple[str, dict[str, float]]]]:
    """The reading of ``records`` (F rows of one length) that fits the images-alone ``T_cam``:
    (its name, its evidence, the other readings' names and evidence, best first). ``forced``:
    the name to take (its evidence is still given). Refuses in one line when none fits, or when
    another reading that gives other poses fits within ``CONVENTION_MARGIN`` of it. ``turn``: as
    :func:`evidence`'s."""
    rows = np.stack(records)
    names = conventions(rows.shape[1])
    if forced is not None and forced not in names:
        raise InputError(f"--convention {forced!r} is not one of: {'; '.join(names)}")
    tried: list[tuple[float, str, np.ndarray, dict[str, float]]] = []
    for name in [forced] if forced else names:
        T = np.stack([pose_of(r, *name.split(", ")) for r in rows])
        if any(np.allclose(T, other, atol=1e-9) for _, _, other, _ in tried):
            continue  # the same poses as a reading before (e.g. no rotation at all)
        e = evidence(T, T_cam, mount, turn)
        tried.append((score(e), name, T, e))
    tried.sort(key=lambda x: x[0])
    best, name, _, e = tried[0]
    others = [(n, ev) for _, n, _, ev in tried[1:]]
    if forced is not None:
        return name, e, others
    figures = "; ".join(f"{n}: {describe(ev)}" for _, n, _, ev in tried[:3])
    if not e["rotated_pairs"]:  # every reading's rotations stand still
        raise InputError(
            f"the images show no rotation between frames, so they cannot tell the rotation "
            f"format or the direction of the poses ({figures}); give the reading meant with "
            "--convention",
            where=where,
        )
    if not best <= 1.0:
        raise InputError(
            f"no reading of the poses fits the images (best: {figures}); check that the rows "
            "pair with the images and that the cell's target and mount are the session's",
            where=where,
        )
    alike = [t for t in tried[1:] if t[0] <= max(CONVENTION_MARGIN * best, 1e-12) and t[0] <= 1.0]
    if alike:
        raise InputError(
            f"{len(alike) + 1} readings of the poses fit the images alike ({figures}): frames "
            "turned about several axes tell them apart; give the one meant with --convention",
            where=where,
        )
    return name, e, others


def _numbers(value: Any, where: str) -> np.ndarray:
    try:
        v = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        v = np.zeros(0)
    if len(v) not in (6, 7, 12, 16) or not np.all(np.isfinite(v)):
        raise InputError(
            f"a pose must be 6 numbers (position, three angles or a rotation vector), 7 "
            f"(position, quaternion), or a 3x4 or 4x4 matrix; got {value!r:.60}",
            where=where,
        )
    return v


def read_rows(path: Path) -> list[tuple[str | None, np.ndarray, str]]:
    """A pose file's rows: (the image named in the row or None, the numbers, where). CSV or
    whitespace; lines without a number before the first row (a header) and ``#`` lines skip."""
    rows: list[tuple[str | None, np.ndarray, str]] = []
    for n, line in enumerate(read_text(path, "pose file").splitlines(), 1):
        tokens = [t for t in re.split(r"[,;\s]+", line.strip()) if t]
        if not tokens or tokens[0].startswith("#"):
            continue
        names = [t for t in tokens if not re.fullmatch(NUMBER, t)]
        if len(names) == len(tokens) and not rows:
            continue  # a header
        where = f"{path.name}: line {n}"
        if len(names) > 1:
            raise InputError(
                f"holds {len(names)} words {names[:3]}; one column may name the image", where
            )
        told = f"{where} ({names[0]!r} read as the image's name)" if names else where
        nums = _numbers([t for t in tokens if t not in names], told)
        rows.append((names[0] if names else None, nums, where))
    if not rows:
        raise InputError("holds no pose rows", where=path.name)
    return rows


def sidecar_rows(directory: Path, key: str | None) -> list[tuple[str | None, np.ndarray, str]]:
    """The pose of each sidecar file (``17.json`` beside ``17.jpg``) in ``directory`` under
    ``key`` or the first of ``POSE_KEYS``."""
    rows = []
    files = [p for p in directory.iterdir() if p.suffix.lower() in SIDECAR_SUFFIXES]
    for p in sorted(files, key=lambda p: natural_key(p.name)):
        data = load_yaml(p, "pose file")
        keys = [key] if key else [k for k in POSE_KEYS if isinstance(data, Mapping) and k in data]
        if not keys:
            raise InputError(
                f"has none of the keys {list(POSE_KEYS)}; name the pose's with --pose-key", p.name
            )
        if not isinstance(data, Mapping) or keys[0] not in data:
            raise InputError(f"has no key {keys[0]!r}", where=p.name)
        rows.append((p.stem, _numbers(data[keys[0]], f"{p.name}: {keys[0]}"), p.name))
    if not rows:
        raise InputError("holds no JSON or YAML pose file", where=str(directory))
    return rows


def pair(
    images: Sequence[Path], rows: Sequence[tuple[str | None, np.ndarray, str]]
) -> tuple[list[tuple[Path, np.ndarray]], list[str], list[str]]:
    """(image, record) pairs, the rows without an image and the images without a row: by the
    name a row gives (its stem against the images' stems), else in order (counts must agree)."""
    if all(r[0] is None for r in rows):
        if len(rows) != len(images):
            raise InputError(
                f"{len(images)} images but {len(rows)} pose rows, paired in order: give each row "
                "the image's name in a column, or remove the extra ones",
                where=rows[0][2].split(":")[0],
            )
        return [(im, r[1]) for im, r in zip(images, rows, strict=True)], [], []
    by_stem = {im.stem: im for im in images}
    pairs, lost_rows = [], []
    for name, numbers, where in rows:
        im = by_stem.get(Path(name or "").stem)
        if im is None:
            lost_rows.append(f"{where} ({name})")
        else:
            pairs.append((im, numbers))
    paired = {im for im, _ in pairs}
    return pairs, lost_rows, [im.name for im in images if im not in paired]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``slidecal import`` options."""
    p.add_argument("images", help="folder of the images (PNG, JPEG), in natural order")
    p.add_argument("poses", help="file of poses, one a row, or the folder of per-image JSON/YAML")
    p.add_argument("--config", required=True, help="cell file: the target and the mount")
    p.add_argument("--out", required=True, help="session directory to write")
    p.add_argument("--pose-key", help=f"sidecar key of the pose (default: first of {POSE_KEYS})")
    p.add_argument(
        "--convention", help="the reading to take, as printed: 'mm, Euler Z-Y-X deg, tool in base'"
    )


def main(args: argparse.Namespace) -> int:
    """Read, find the convention, write the session, print the choice and its evidence."""
    cfg = load_config(args.config)
    folder, poses = Path(args.images), Path(args.poses)
    images = sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES),
        key=lambda p: natural_key(p.name),
    )
    if not images:
        raise InputError("holds no PNG or JPEG image", where=str(folder))
    rows = sidecar_rows(poses, args.pose_key) if poses.is_dir() else read_rows(poses)
    if len({len(r[1]) for r in rows}) > 1:
        raise InputError("rows of different lengths: one convention per file", where=poses.name)
    pairs, lost_rows, lost_images = pair(images, rows)
    name = cfg.reference_camera
    shots, unreadable, sizes = [], [], set()
    for path, numbers in pairs:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            unreadable.append(path.name)
            det = Detection(np.zeros(0), np.zeros((0, 2)), "the image cannot be read")
        else:
            sizes.add(img.shape[1::-1])
            det = detect(img, cfg.target).detection
        shots.append((path, numbers, img, det))
    if len(sizes) != 1:
        raise InputError(
            f"images of {len(sizes)} sizes {sorted(sizes)}: import one camera's at a time",
            str(folder),
        )
    spec = CameraSpec(name, *sizes.pop())
    frames = tuple(Frame(k, {name: s[3]}) for k, s in enumerate(shots))
    seen = CalibrationProblem(cfg.target, (spec,), frames, cfg.mount, "none")
    T_cam = board_poses(seen, name)
    idx = list(T_cam)
    if len(idx) < 3:
        raise InputError(
            f"the cell's target was found in {len(idx)} image(s); at least 3 are needed (is the "
            "target of --config the one in the images?)",
            str(folder),
        )
    turn = half_turn_T(cfg.target) if half_turn_symmetric(cfg.target) else None
    chosen, e, others = find_convention(
        [shots[k][1] for k in idx],
        [T_cam[k] for k in idx],
        cfg.mount,
        args.convention,
        poses.name,
        turn,
    )
    unit, rotation, direction = chosen.split(", ")
    report = {
        "images": str(folder),
        "poses": str(poses),
        "paired": "in order" if all(r[0] is None for r in rows) else "by name",
        "convention": {"units": unit, "rotation": rotation, "direction": direction},
        "evidence": {k: round(v, 6) if isinstance(v, float) else v for k, v in e.items()},
        "next": {"convention": others[0][0], "evidence": describe(others[0][1])}
        if others
        else None,
        "rows_without_image": lost_rows,
        "images_without_row": lost_images,
        "unreadable_images": unreadable,
    }
    w = SessionWriter(
        args.out,
        cfg.target,
        (spec,),
        mount=cfg.mount,
        options=cfg.options,
        extra={"import": report},
    )
    for _, numbers, img, det in shots:
        T = pose_of(numbers, unit, rotation, direction)
        w.append_frame(T, images=None if img is None else {name: img}, detections={name: det})
    w.finish()
    found = sum(1 for s in shots if len(s[3].ids))
    print(
        f"slidecal import: {len(pairs)} images paired with poses {report['paired']}, the board "
        f"found in {found}"
    )
    print(f"  poses read as: {chosen}")
    print(f"  evidence: {describe(e)}")
    if others:
        print(f"  next best: {others[0][0]}: {describe(others[0][1])}")
    for what, names in (
        ("rows without an image", lost_rows),
        ("images without a row", lost_images),
        ("unreadable images", unreadable),
    ):
        if names:
            print(f"  {what}: {', '.join(names)}")
    print(f"  wrote {args.out}; next: slidecal solve {args.out}")
    return 0

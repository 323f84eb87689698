"""The install store: where the calibration in use lives, with its history and a rollback
(``slidecal rollback``); its layout, atomic installs and refusals: docs/UNATTENDED.md.
"""

from __future__ import annotations

import os
import shutil
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from slidecal.routines.ops.lock import Lock
from slidecal.routines.results_io import read_result
from slidecal.routines.schema import _fsync_dir, dump_yaml, load_yaml, write_atomic
from slidecal.routines.session import load_session
from slidecal.solver.errors import InputError
from slidecal.solver.problem import CalibrationProblem
from slidecal.solver.result import CalibrationResult

CURRENT = "current"
HISTORY = "history"
ROLLED_BACK = "ROLLED_BACK"
INSTALLED_FILE = "installed.yaml"
SESSION_FILE = "session.yaml"
#: A new result is "worse" when one of its one-sigmas exceeds the installed one's by this factor.
WORSE_FACTOR = 1.25

#: What an install keeps of the session directory (``detections.npy``: the corners its
#: ``session.yaml`` counts, which ``slidecal check`` compares with)
_FILES = (
    "result.yaml",
    "summary.txt",
    "verdict.yaml",
    "plan.yaml",
    "report.html",
    "report.png",
    "detections.npy",
)


class NotInstalled(InputError):
    """The result was not installed (rejected, drifted, or worse than the installed one)."""


def current_dir(store: str | Path) -> Path | None:
    """The directory ``current`` points at, or None when nothing is installed."""
    cur = Path(store) / CURRENT
    if not cur.exists():
        return None
    return cur.resolve()


def installed_result(store: str | Path) -> CalibrationResult | None:
    """The installed calibration (``current/result.yaml``), or None."""
    d = current_dir(store)
    if d is None:
        return None
    return read_result(d / "result.yaml")


def installed_session(directory: str | Path) -> CalibrationProblem | None:
    """The frames of the installed session kept in an install's ``directory`` (its
    ``session.yaml``: measured robot poses and detections), or None when it keeps none."""
    d = Path(directory)
    if not (d / SESSION_FILE).is_file():
        return None
    return load_session(d, detect_images=False).problem


def installed_info(directory: str | Path | None) -> dict[str, Any]:
    """An install's ``installed.yaml`` (empty when there is none)."""
    meta = Path(directory) / INSTALLED_FILE if directory else None
    data = load_yaml(meta, "installed.yaml") if meta is not None and meta.is_file() else None
    return data if isinstance(data, dict) else {}


def _session_copy(src: Path) -> str | None:
    """The text of ``src/session.yaml`` without its frames' image paths (None when there is
    no session file or no frame holds detections: nothing a check could compare with)."""
    if not (src / SESSION_FILE).is_file():
        return None
    data = load_yaml(src / SESSION_FILE, "session.yaml")
    frames = data.get("frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or not any(
        isinstance(f, dict) and f.get("detections") for f in frames
    ):
        return None
    doc = dict(data)
    doc["frames"] = [
        {k: v for k, v in f.items() if k != "images"} if isinstance(f, dict) else f for f in frames
    ]
    return dump_yaml(doc)


def check_same_cell(
    installed: CalibrationResult, path: str | None, cameras: Any, cell: str | None
) -> None:
    """Refuse (InputError: nothing compared, nothing moved) an installed calibration of another
    cell or camera: the cell its ``installed.yaml`` names against ``cell``, and the image size of
    each of ``cameras`` (``name``, ``width``, ``height``) the installed calibration also has."""
    old_cell = installed_info(path).get("cell")
    if cell and old_cell and str(old_cell) != str(cell):
        raise InputError(
            f"holds the calibration of cell {old_cell}, not of this cell ({cell}): nothing was "
            "compared; give this cell's install store",
            where=str(path),
        )
    for c in cameras:
        old = installed.cameras.get(c.name)
        if old is not None and (old.width, old.height) != (c.width, c.height):
            raise InputError(
                f"holds camera {c.name!r} at {old.width}x{old.height}, this one is "
                f"{c.width}x{c.height}: another camera, not a drift; nothing was compared; give "
                "this camera's install store or result",
                where=str(path),
            )


def history(store: str | Path) -> list[Path]:
    """Every install, oldest first."""
    h = Path(store) / HISTORY
    if not h.is_dir():
        return []
    return sorted(p for p in h.iterdir() if p.is_dir() and not p.name.startswith("."))


def one_sigmas(r: CalibrationResult) -> dict[str, float]:
    """The finite one-sigmas of a result: ``<cam>.fx_rel`` (relative), ``<cam>.cx_px``,
    ``<transform>.rot_deg``, ``<transform>.t_mm``."""
    out: dict[str, float] = {}
    for n, c in r.cameras.items():
        K = np.asarray(c.K, dtype=float)
        for p, v in (("fx", K[0, 0]), ("fy", K[1, 1])):
            s = c.std.get(p)
            if s is not None and np.isfinite(s):
                out[f"{n}.{p}_rel"] = float(s) / abs(v)
        for p in ("cx", "cy"):
            s = c.std.get(p)
            if s is not None and np.isfinite(s):
                out[f"{n}.{p}_px"] = float(s)
    for t in ([r.hand_eye] if r.hand_eye is not None else []) + list(r.rig.values()):
        if t.std_rot_deg is not None and np.isfinite(t.std_rot_deg):
            out[f"{t.name}.rot_deg"] = float(t.std_rot_deg)
        if t.t_m is not None and t.std_t_mm is not None and np.isfinite(t.std_t_mm):
            out[f"{t.name}.t_mm"] = float(t.std_t_mm)
    return out


def worse_than(new: CalibrationResult, old: CalibrationResult) -> str | None:
    """Why ``new`` is less certain than ``old`` (one line), or None when it is not."""
    a, b = one_sigmas(new), one_sigmas(old)
    worst = None
    for k in a:
        if k in b and b[k] > 0 and a[k] > WORSE_FACTOR * b[k]:
            r = a[k] / b[k]
            if worst is None or r > worst[1]:
                worst = (k, r)
    if worst is None:
        return None
    return (
        f"its {worst[0]} one-sigma is {worst[1]:.2f} times the installed one's "
        f"(more than {WORSE_FACTOR:g})"
    )


def _publish_link(store: Path, target: Path) -> None:
    tmp = store / f".{CURRENT}.tmp"
    tmp.unlink(missing_ok=True)  # a link left by an install that died here
    os.symlink(os.path.relpath(target, store), tmp)
    os.replace(tmp, store / CURRENT)
    _fsync_dir(store)


def install(
    store: str | Path,
    source_dir: str | Path,
    result: CalibrationResult,
    verdict: str,
    force: bool = False,
    accept_drift: bool = False,
    info: dict[str, Any] | None = None,
) -> Path:
    """Install the solved session ``source_dir`` (its result, exports, verdict, report) into
    ``store``; return the new install's directory. Raises :class:`NotInstalled` with the
    reason when the result must not replace the installed one."""
    store = Path(store)
    src = Path(source_dir)
    if verdict == "rejected":
        raise NotInstalled(
            "the result was rejected; the installed calibration stays", where=str(store)
        )
    if verdict == "drifted" and not accept_drift:
        raise NotInstalled(
            "the result differs from the installed calibration (drifted); look at the report, "
            "then run again with --accept-drift (or install: {accept_drift: true} in the cell "
            "file) to install such a result",
            where=str(store),
        )
    if store.exists() and not store.is_dir():
        raise InputError("is a file; --install needs a directory", where=str(store))
    try:
        (store / HISTORY).mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot be created ({e.strerror}); check the path", str(store)) from None
    with Lock(store / ".lock", f"the install store {store}"):
        old = installed_result(store)
        if old is not None and not force:
            why = worse_than(result, old)
            if why is not None:
                raise NotInstalled(
                    f"the new result is less certain than the installed one: {why}; install "
                    "it anyway with --force",
                    where=str(store),
                )
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S_%fZ")
        staging = store / f".staging-{stamp}"
        staging.mkdir()
        try:
            for name in _FILES:
                if (src / name).is_file():
                    write_atomic(staging / name, (src / name).read_bytes())
            exp = src / "export"
            if exp.is_dir():
                (staging / "export").mkdir()
                for p in sorted(exp.iterdir()):
                    if p.is_file():
                        write_atomic(staging / "export" / p.name, p.read_bytes())
            session_text = _session_copy(src)
            if session_text is not None:
                write_atomic(staging / SESSION_FILE, session_text)
            meta = {
                "installed_utc": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "session": str(src.resolve()),
                "verdict": verdict,
                "forced": bool(force),
                **(info or {}),
            }
            write_atomic(staging / INSTALLED_FILE, dump_yaml(meta))  # each write syncs staging
            final = store / HISTORY / stamp
            os.replace(staging, final)
            _fsync_dir(store / HISTORY)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        _publish_link(store, final)
        return final


def rollback(store: str | Path) -> tuple[Path, Path]:
    """Point ``current`` at the install before it; return (left, now current)."""
    store = Path(store)
    if not store.is_dir():
        raise InputError("is not an install store (no such directory)", where=str(store))
    with Lock(store / ".lock", f"the install store {store}"):
        cur = current_dir(store)
        if cur is None:
            raise InputError("has nothing installed; nothing to roll back", where=str(store))
        entries = history(store)
        older = [p for p in entries if p.name < cur.name and not (p / ROLLED_BACK).exists()]
        if not older:
            raise InputError(
                f"has no install before {cur.name}; nothing to roll back to", where=str(store)
            )
        prev = older[-1]
        write_atomic(
            cur / ROLLED_BACK,
            f"rolled back at {datetime.now(UTC).strftime('%Y-%m-%dT%H:%M:%SZ')}\n",
        )
        _publish_link(store, prev)
        return cur, prev


# ----------------------------------------------------------------------------- command line

help = "restore the install store's previous calibration (slidecal rollback STORE)"


def add_arguments(p) -> None:  # noqa: ANN001 - argparse parser
    """``slidecal rollback STORE``."""
    p.add_argument("store", help="the install store (the directory given to --install)")


def main(args) -> int:  # noqa: ANN001 - argparse namespace
    """Roll back and say what is installed now."""
    left, now = rollback(args.store)
    print(f"rolled back {left.name}; installed now: {now.name} ({Path(args.store) / CURRENT})")
    return 0

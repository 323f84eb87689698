"""The bad-input table: malformed cell, plan, session and result files, and how each is refused.

The cases are data (``tests/data/bad_input.yaml``); this module runs them. Every case
writes a valid file of its kind, breaks one thing in it, and feeds it to slidecal the
way a user would (``slidecal plan --config``, ``slidecal run --plan``, ``slidecal solve``, or
the result reader). Each must be refused with exit code 2 and one line on stderr naming the file
and the field, no traceback, and no output file. ``tests/test_bad_input.py`` runs the table;
``python -m tests.bench bad_input`` runs it too and writes the page with each case's message.
"""

from __future__ import annotations

import contextlib
import copy
import io
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from slidecal.routines import cli
from slidecal.routines.config import CELL_KEYS
from slidecal.routines.config import PLAN_KEYS as PLANNER_KEYS
from slidecal.routines.plan import PLAN_KEYS
from slidecal.routines.results_io import RESULT_KEYS, RESULT_PART_KEYS, read_result
from slidecal.routines.schema import dump_yaml, parse_yaml
from slidecal.routines.session import OPTIONS_KEYS, SESSION_KEYS, TARGET_KEYS
from slidecal.solver.errors import InputError

DELETE = object()
#: the cases, as data
TABLE = Path(__file__).parent / "data" / "bad_input.yaml"


@dataclass(frozen=True)
class Case:
    """One malformed input.

    ``kind``: cell | plan | session | result; ``changes``: (path of keys/indices, value or
    :data:`DELETE`) applied to the valid file; ``text``: replaces the file's text (bytes allowed)
    when given; ``field``: what the message must name after the file (``options.robot_noise_mmm``).
    ``base``: which valid file to start from (``real``: a cell naming a UR and an OAK).
    """

    name: str
    kind: str
    field: str
    changes: tuple[tuple[tuple[Any, ...], Any], ...] = ()
    text: Callable[[str], str | bytes] | None = None
    base: str = "simulated"
    renames: tuple[tuple[tuple[Any, ...], str], ...] = ()


# ----------------------------------------------------------------------------- valid files


def _cell(base: str) -> dict[str, Any]:
    text = resources.files("slidecal.mocks").joinpath("default_cell.yaml").read_text("utf-8")
    d = parse_yaml(text, "default_cell.yaml")
    if base == "real":
        del d["simulation"]
        d["robot"] = {"driver": "ur", "host": "192.0.2.10", "model": "UR5e"}
        d["cameras"] = {
            "driver": "oak",
            "reference": "left",
            "list": [
                {"name": "left", "width": 1280, "height": 800, "socket": "CAM_B"},
                {"name": "right", "width": 1280, "height": 800, "socket": "CAM_C"},
            ],
        }
    return d


_POSE = [-0.40, 0.0, 0.545, 3.14159265, 0.0, 0.0]


def _plan() -> dict[str, Any]:
    g = [[_POSE, [-0.38, 0.0, 0.545, 3.14159265, 0.0, 0.0]]] * 3
    return {
        "format": "slidecal.plan/1",
        "speed_mps": 0.25,
        "accel_mps2": 1.0,
        "settle_s": 0.5,
        "groups": [list(x) for x in g],
        "via": _POSE,
        "predicted_std": {"cam.fx_px": 0.3},
        "duration_s": 40.0,
        "notes": ["a plan"],
    }


def _session() -> dict[str, Any]:
    def det() -> dict[str, Any]:
        return {"cam": {"ids": [0, 1, 2], "px": [[100.0, 100.0], [150.0, 100.0], [200.0, 100.0]]}}

    return {
        "format": "slidecal.session/1",
        "status": "complete",
        "mount": "eye_in_hand",
        "knowledge": "robot",
        "target": {
            "kind": "charuco",
            "squares_x": 11,
            "squares_y": 8,
            "square_size_m": 0.03,
            "marker_size_m": 0.022,
            "dictionary": "DICT_5X5_100",
        },
        "cameras": [{"name": "cam", "width": 1280, "height": 800}],
        "reference_camera": "cam",
        "options": {"skew": False, "distortion": [True, True, True, True, False]},
        "cell": "cell.yaml",
        "frames": [
            {"id": 0, "group": 0, "T_base_tool": list(_POSE), "detections": det()},
            {"id": 1, "group": 0, "T_base_tool": list(_POSE), "detections": det()},
        ],
        "events": [],
    }


def _result() -> dict[str, Any]:
    eye = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    K = [[880.0, 0.0, 640.0], [0.0, 880.0, 400.0], [0.0, 0.0, 1.0]]
    T = {"R": eye, "t_m": [0.03, -0.06, 0.045], "std_rot_deg": 0.01, "std_t_mm": 0.1}
    return {
        "format": "slidecal.result/1",
        "cameras": {
            "cam": {
                "width": 1280,
                "height": 800,
                "K": K,
                "distortion_model": "opencv5",
                "distortion": [-0.12, 0.05, 0.0, 0.0, 0.0],
                "std": {"fx": 0.2, "fy": 0.2},
                "reproj_rms_px": 0.05,
            }
        },
        "T_tool_cam": T,
        "T_base_board": dict(T),
        "mount": "eye_in_hand",
        "reference_camera": "cam",
        "converged": True,
        "iterations": 7,
        "reprojection": {
            "rms_px": 0.05,
            "sigma_px": 0.05,
            "per_image": [{"frame": 0, "camera": "cam", "rms_px": 0.05}],
        },
        "unobservable": {},
        "messages": [],
        "scale_checks": [
            {"frame_a": 0, "frame_b": 1, "robot_mm": 50.0, "camera_mm": 50.1, "ratio": 1.002}
        ],
        "scale_check": {"median_ratio": 1.002, "worst_ratio": 1.002, "n": 1},
        "H_inf": {},
        "outliers": [[0, "cam", 3]],
        "linear": {"cam": K},
        "parameter_names": ["cam.fx", "cam.fy"],
        "covariance": [[0.04, 0.0], [0.0, 0.04]],
    }


FILE_NAMES = {"cell": "cell.yaml", "plan": "plan.yaml", "session": "session.yaml"}


def valid_data(kind: str, base: str = "simulated") -> dict[str, Any]:
    """The valid file each case starts from (a fresh copy)."""
    make = {"cell": lambda: _cell(base), "plan": _plan, "session": _session, "result": _result}
    return copy.deepcopy(make[kind]())


def _apply(data: Any, case: Case) -> Any:
    for path, new in case.renames:
        node = data
        for k in path[:-1]:
            node = node[k]
        node[new] = node.pop(path[-1])
    for path, value in case.changes:
        node = data
        for k in path[:-1]:
            if isinstance(node, dict) and k not in node:
                node[k] = {}
            node = node[k]
        if value is DELETE:
            del node[path[-1]]
        else:
            node[path[-1]] = value
    return data


# ----------------------------------------------------------------------------- running a case


@dataclass(frozen=True)
class Outcome:
    """What slidecal did with a case: exit code, stderr, files it left behind."""

    code: int
    stderr: str
    leftovers: tuple[str, ...]


def run_case(case: Case, directory: Path) -> Outcome:
    """Write the case's files under ``directory`` and feed them to slidecal."""
    directory.mkdir(parents=True, exist_ok=True)
    data = _apply(valid_data(case.kind, case.base), case)
    text: str | bytes = dump_yaml(data)
    if case.text is not None:
        text = case.text(text)  # type: ignore[arg-type]
    out = directory / "out"
    if case.kind == "result":
        return _read_result_case(directory / "result.yaml", text)
    if case.kind == "session":
        target = directory / "session"
        target.mkdir()
        argv = ["solve", str(target), "--out", str(out / "result.yaml"), "--quiet"]
    elif case.kind == "plan":
        target = directory / "plan.yaml"
        argv = ["run", "--plan", str(target), "--out", str(out), "--quiet", "--no-recording"]
    else:
        target = directory / "cell.yaml"
        argv = ["plan", "--config", str(target), "--out", str(out / "plan.yaml"), "--quiet"]
    file = target / "session.yaml" if case.kind == "session" else target
    file.write_bytes(text.encode("utf-8") if isinstance(text, str) else text)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            code = cli.main(argv)
        except Exception as e:  # noqa: BLE001 - the table reports an escaped exception as such
            code, err = -1, io.StringIO(f"Traceback: {type(e).__name__}: {e}\n")
    left = (
        tuple(sorted(str(p.relative_to(directory)) for p in out.rglob("*"))) if out.exists() else ()
    )
    if out.exists() and not left:
        left = ("out/",)
    return Outcome(code, err.getvalue(), left)


def _read_result_case(path: Path, text: str | bytes) -> Outcome:
    path.write_bytes(text.encode("utf-8") if isinstance(text, str) else text)
    try:
        read_result(path)
    except InputError as e:
        return Outcome(2, f"slidecal: {' '.join(str(e).split())}\n", ())
    except Exception as e:  # noqa: BLE001
        return Outcome(-1, f"Traceback: {type(e).__name__}: {e}\n", ())
    return Outcome(0, "", ())


def expected_where(case: Case) -> str:
    """``file: field`` the message must contain."""
    file = FILE_NAMES.get(case.kind, "result.yaml")
    return f"{file}: {case.field}" if case.field else file


# ----------------------------------------------------------------------------- the table


def _typo(key: str) -> str:
    """A plausible misspelling: the last letter doubled."""
    return key + key[-1]


def _typos(kind: str, section: tuple[Any, ...], keys: tuple[str, ...], base: str = "simulated"):
    """One case per key of a section: the key misspelt (its value kept when present)."""
    data = valid_data(kind, base)
    node = data
    for k in section:
        node = node[k]
    prefix = ".".join(_label(k) for k in section)
    cases = []
    for key in keys:
        if key == "format" and kind != "cell":
            continue  # a file without its format is refused as such (cases below)
        label = f"{prefix}.{_typo(key)}" if prefix else _typo(key)
        label = label.replace(".[", "[")
        if key in node:
            cases.append(
                Case(
                    f"{kind}: typo {label}",
                    kind,
                    label,
                    renames=(((*section, key), _typo(key)),),
                    base=base,
                )
            )
        else:
            cases.append(
                Case(
                    f"{kind}: typo {label}", kind, label, (((*section, _typo(key)), 1),), base=base
                )
            )
    return cases


def _label(k: Any) -> str:
    return f"[{k}]" if isinstance(k, int) else str(k)


def _edit_text(ops: dict[str, Any]) -> Callable[[str], str | bytes]:
    """A case's ``text:`` edit (docs at the top of bad_input.yaml) as a function of the text."""

    def edit(text: str) -> str | bytes:
        if "text" in ops:
            text = ops["text"]
        if "duplicate" in ops:
            text += next(ln for ln in text.splitlines() if ln.startswith(f"{ops['duplicate']}:"))
            text += "\n"
        if "replace" in ops:
            text = text.replace(*ops["replace"], 1)
        text += ops.get("append", "")
        if "prepend_bytes" in ops:
            return ops["prepend_bytes"].encode("latin-1").decode("unicode_escape").encode(
                "latin-1"
            ) + text.encode()
        return text.encode(ops["encoding"]) if "encoding" in ops else text

    return edit


#: the schema's key tables a ``typos`` item names
SCHEMA_KEYS = {"CELL_KEYS": CELL_KEYS, "PLAN_KEYS": PLAN_KEYS, "PLANNER_KEYS": PLANNER_KEYS,
               "RESULT_KEYS": RESULT_KEYS, "RESULT_PART_KEYS": RESULT_PART_KEYS,
               "OPTIONS_KEYS": OPTIONS_KEYS, "SESSION_KEYS": SESSION_KEYS,
               "TARGET_KEYS": TARGET_KEYS}


def _keys(spec: str | list[str]) -> tuple[str, ...]:
    """A ``typos`` item's keys: a list, or a schema table (``CELL_KEYS[robot]``)."""
    if isinstance(spec, list):
        return tuple(spec)
    name, _, index = spec.partition("[")
    table = SCHEMA_KEYS[name]
    return tuple(table[index[:-1]] if index else table)


def _case(item: dict[str, Any]) -> Case:
    changes = tuple((tuple(c["at"]), DELETE if c.get("delete") else c["value"])
                    for c in item.get("changes", ()))
    renames = tuple((tuple(r["at"]), r["to"]) for r in item.get("renames", ()))
    text = _edit_text(item["text"]) if "text" in item else None
    return Case(item["name"], item["kind"], item["field"], changes, text,
                item.get("base", "simulated"), renames)


def _cases() -> list[Case]:
    cases: list[Case] = []
    for item in yaml.safe_load(TABLE.read_text(encoding="utf-8"))["cases"]:
        if "typos" in item:
            cases += _typos(item["typos"], tuple(item["at"]), _keys(item["keys"]),
                            item.get("base", "simulated"))
        else:
            cases.append(_case(item))
    return cases


CASES: tuple[Case, ...] = ()


def cases() -> tuple[Case, ...]:
    """Every case of the table (built once)."""
    global CASES
    if not CASES:
        CASES = tuple(_cases())
    return CASES


def missing_file_outcomes(directory: Path) -> list[tuple[str, Outcome]]:
    """Files named on the command line that are missing or not files."""
    directory.mkdir(parents=True, exist_ok=True)
    out = directory / "out"
    runs = {
        "cell file missing": ["plan", "--config", str(directory / "nope.yaml"), "--out", str(out)],
        "cell file is a directory": ["plan", "--config", str(directory), "--out", str(out)],
        "plan file missing": ["run", "--plan", str(directory / "nope.yaml"), "--out", str(out)],
        "session directory missing": ["solve", str(directory / "nope"), "--out", str(out)],
        "session directory without session.yaml": ["solve", str(directory), "--out", str(out)],
    }
    results = []
    for name, argv in runs.items():
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = cli.main(argv)
        results.append((name, Outcome(code, err.getvalue(), ("out",) if out.exists() else ())))
    return results


def table_markdown() -> str:
    """``docs/results/BAD_INPUT.md``: every case and the line slidecal answers it with."""
    rows = []
    n_ok = 0
    with tempfile.TemporaryDirectory() as tmp:
        for i, case in enumerate(cases()):
            o = run_case(case, Path(tmp) / f"c{i}")
            ok = _clean(o) and expected_where(case) in o.stderr
            n_ok += ok
            rows.append((case.kind, case.name, o, ok))
        for name, o in missing_file_outcomes(Path(tmp) / "missing"):
            ok = _clean(o)
            n_ok += ok
            rows.append(("command line", name, o, ok))
        rows = [
            (k, n, Outcome(o.code, o.stderr.replace(tmp, "DIR"), o.leftovers), ok)
            for k, n, o, ok in rows
        ]
    lines = [
        "# Bad input: what slidecal answers",
        "",
        "Generated by `python -m tests.bench bad_input` (do not edit by",
        "hand); `tests/test_bad_input.py` runs the same table. Each case starts from a valid file,",
        "breaks one thing and feeds it to slidecal as a user would: cell files through",
        "`slidecal plan --config`, plan files through `slidecal run --plan`, sessions through",
        "`slidecal solve`, result files through the result reader. Every case must exit with",
        "code 2 and one line on stderr naming the file and the field, with no traceback and no",
        "output file.",
        "",
        f"{n_ok} of {len(rows)} cases refused cleanly.",
        "",
        "| # | file | case | exit | message |",
        "| --- | --- | --- | --- | --- |",
    ]
    for i, (kind, name, o, ok) in enumerate(rows, 1):
        msg = o.stderr.strip().replace("|", "\\|")
        mark = "" if ok else " **(not clean)**"
        lines.append(f"| {i} | {kind} | {name}{mark} | {o.code} | `{msg}` |")
    return "\n".join(lines) + "\n"


def _clean(o: Outcome) -> bool:
    return (
        o.code == 2
        and o.stderr.startswith("slidecal: ")
        and o.stderr.count("\n") == 1
        and "Traceback" not in o.stderr
        and not o.leftovers
    )

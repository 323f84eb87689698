"""The bad-input table: malformed cell, plan, session and result files, and how each is refused.

Every case writes a valid file of its kind, breaks one thing in it, and feeds it to slidecal the
way a user would (``slidecal plan --config``, ``slidecal run --plan``, ``slidecal solve``, or
the result reader). Each must be refused with exit code 2 and one line on stderr naming the file
and the field, no traceback, and no output file. ``tests/test_bad_input.py`` runs the table;

    python -m slidecal.routines.bad_input docs/BAD_INPUT.md

runs it too and writes the table with the message of each case.
"""

from __future__ import annotations

import contextlib
import copy
import io
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from slidecal.routines.schema import dump_yaml

DELETE = object()


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
    from importlib import resources

    from slidecal.routines.schema import parse_yaml

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
    from slidecal.routines import cli

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
    from slidecal.routines.results_io import read_result
    from slidecal.solver.errors import InputError

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


def _dup(kind: str, key: str) -> Callable[[str], str]:
    def f(text: str) -> str:
        line = next(ln for ln in text.splitlines() if ln.startswith(f"{key}:"))
        return text + line + "\n"

    return f


def _cases() -> list[Case]:
    from slidecal.routines.config import CELL_KEYS
    from slidecal.routines.config import PLAN_KEYS as PLANNER_KEYS
    from slidecal.routines.plan import PLAN_KEYS
    from slidecal.routines.results_io import RESULT_KEYS, RESULT_PART_KEYS
    from slidecal.routines.session import OPTIONS_KEYS, SESSION_KEYS, TARGET_KEYS

    nan, inf = float("nan"), float("inf")
    cases: list[Case] = []
    # -- typos in every section
    cases += _typos("cell", (), CELL_KEYS[""])
    cases += _typos("cell", ("robot",), CELL_KEYS["robot"])
    cases += _typos("cell", ("robot", "workspace"), CELL_KEYS["robot.workspace"])
    cases += _typos("cell", ("cameras",), ("driver", "reference"))
    cases += _typos("cell", ("cameras", "list", 0), CELL_KEYS["cameras.list[].oak"], base="real")
    cases += _typos("cell", ("target",), TARGET_KEYS["charuco"])
    cases += _typos("cell", ("approximate",), CELL_KEYS["approximate.eye_in_hand"])
    cases += _typos("cell", ("simulation",), ("seed", "camera_preset", "noise", "target_jitter"))
    cases += _typos("cell", ("simulation", "noise"), CELL_KEYS["simulation.noise"])
    cases += _typos("cell", ("simulation", "target_jitter"), CELL_KEYS["simulation.target_jitter"])
    cases += _typos("cell", ("approximate", "T_tool_cam"), ("rpy_deg",))
    cases.append(  # t_m's doubled letter is t_mm, a key of its own: a dropped underscore
        Case(
            "cell: misspelt approximate.T_tool_cam.tm",
            "cell",
            "approximate.T_tool_cam.tm",
            renames=((("approximate", "T_tool_cam", "t_m"), "tm"),),
            base="simulated",
        )
    )
    cases += _typos("cell", ("plan",), PLANNER_KEYS)
    cases += _typos("cell", ("options",), OPTIONS_KEYS)
    cases += _typos("plan", (), PLAN_KEYS)
    cases += _typos("session", (), SESSION_KEYS[""])
    cases += _typos("session", ("cameras", 0), SESSION_KEYS["cameras[]"])
    cases += _typos("session", ("frames", 0), SESSION_KEYS["frames[]"])
    cases += _typos("session", ("frames", 0, "detections", "cam"), SESSION_KEYS["detection"])
    cases += _typos("session", ("options",), OPTIONS_KEYS)
    cases += _typos("result", (), RESULT_KEYS)
    cases += _typos("result", ("cameras", "cam"), RESULT_PART_KEYS["cameras.*"])
    cases += _typos("result", ("T_tool_cam",), RESULT_PART_KEYS["transform"])
    cases += _typos("result", ("reprojection",), RESULT_PART_KEYS["reprojection"])

    C = Case
    cases += [
        # -- files that are not YAML, not UTF-8, duplicated keys, empty
        C(
            "cell file not UTF-8 (Latin-1 comment)",
            "cell",
            "",
            text=lambda t: b"# K\xf6ln\n" + t.encode(),
        ),
        C("plan file not UTF-8", "plan", "", text=lambda t: t.encode("utf-16")),
        C("session file not UTF-8", "session", "", text=lambda t: b"\xff\xfe" + t.encode()),
        C("result file not UTF-8", "result", "", text=lambda t: b"\x80" + t.encode()),
        C("duplicate top-level key in a cell", "cell", "mount", text=_dup("cell", "mount")),
        C("duplicate key in a plan", "plan", "speed_mps", text=_dup("plan", "speed_mps")),
        C("duplicate key in a session", "session", "status", text=_dup("session", "status")),
        C("duplicate key in a result", "result", "mount", text=_dup("result", "mount")),
        C(
            "duplicate key inside a section",
            "cell",
            "robot.model",
            text=lambda t: t.replace("robot:\n", "robot:\n  model: UR10e\n", 1),
        ),
        C("cell file not valid YAML", "cell", "", text=lambda t: t + "robot: [unclosed\n"),
        C("plan file not valid YAML", "plan", "", text=lambda t: "groups: {\n"),
        C("session with a tab indent", "session", "", text=lambda t: t.replace("  ", "\t", 1)),
        C("empty cell file", "cell", "", text=lambda t: ""),
        C("empty plan file", "plan", "", text=lambda t: "# nothing\n"),
        C("cell file is a list", "cell", "", text=lambda t: "- robot\n- cameras\n"),
        C("session file is a number", "session", "", text=lambda t: "42\n"),
        C("result file is text", "result", "", text=lambda t: "just words\n"),
        C(
            "python tag in a cell",
            "cell",
            "",
            text=lambda t: t + "x: !!python/object:os.system {}\n",
        ),
        # -- cell: wrong types, bad numbers, choices
        C("mount misspelt", "cell", "mount", ((("mount",), "eye_in_hnd"),)),
        C("format of another version", "cell", "format", ((("format",), "slidecal.cell/2"),)),
        C("robot is a list", "cell", "robot", ((("robot",), ["ur"]),)),
        C("robot driver unknown", "cell", "robot.driver", ((("robot", "driver"), "fanuc"),)),
        C("UR without host", "cell", "robot.host", ((("robot", "host"), DELETE),), base="real"),
        C("host is a number", "cell", "robot.host", ((("robot", "host"), 10),), base="real"),
        C("host on a simulated robot", "cell", "robot.host", ((("robot", "host"), "10.0.0.2"),)),
        C("robot model unknown", "cell", "robot.model", ((("robot", "model"), "UR7"),)),
        C("speed as text", "cell", "robot.speed_mps", ((("robot", "speed_mps"), "fast"),)),
        C("speed NaN", "cell", "robot.speed_mps", ((("robot", "speed_mps"), nan),)),
        C("speed too high", "cell", "robot.speed_mps", ((("robot", "speed_mps"), 3.0),)),
        C("accel negative", "cell", "robot.accel_mps2", ((("robot", "accel_mps2"), -1.0),)),
        C("accel inf", "cell", "robot.accel_mps2", ((("robot", "accel_mps2"), inf),)),
        C("settle negative", "cell", "robot.settle_s", ((("robot", "settle_s"), -0.5),)),
        C("settle boolean", "cell", "robot.settle_s", ((("robot", "settle_s"), True),)),
        C(
            "start pose of 5 numbers",
            "cell",
            "robot.start_pose",
            ((("robot", "start_pose"), _POSE[:5]),),
        ),
        C(
            "start pose in millimetres",
            "cell",
            "robot.start_pose",
            ((("robot", "start_pose"), [-400.0, 0.0, 545.0, 3.14, 0.0, 0.0]),),
        ),
        C(
            "start pose with text",
            "cell",
            "robot.start_pose",
            ((("robot", "start_pose"), [0, 0, "z", 0, 0, 0]),),
        ),
        C("tcp of 3 numbers", "cell", "robot.tcp", ((("robot", "tcp"), [0, 0, 0.1]),)),
        C(
            "start_q in degrees",
            "cell",
            "robot.start_q",
            ((("robot", "start_q"), [0, -90, 90, -90, -90, 0]),),
        ),
        C(
            "start_q on a real robot",
            "cell",
            "robot.start_q",
            ((("robot", "start_q"), [0, -1.57, 1.57, -1.57, -1.57, 0]),),
            base="real",
        ),
        C(
            "workspace min above max",
            "cell",
            "robot.workspace.max_m",
            ((("robot", "workspace"), {"min_m": [0, 0, 1], "max_m": [1, 1, 0]}),),
        ),
        C(
            "workspace of 2 numbers",
            "cell",
            "robot.workspace.min_m",
            ((("robot", "workspace", "min_m"), [0, 0]),),
        ),
        C("workspace is a list", "cell", "robot.workspace", ((("robot", "workspace"), [0, 1]),)),
        C(
            "limits typo",
            "cell",
            "robot.limits.max_sped_mps",
            ((("robot", "limits"), {"max_sped_mps": 1.0}),),
        ),
        C(
            "limit negative",
            "cell",
            "robot.limits.max_speed_mps",
            ((("robot", "limits"), {"max_speed_mps": -1.0}),),
        ),
        C("camera driver unknown", "cell", "cameras.driver", ((("cameras", "driver"), "gige"),)),
        C(
            "OAK cameras on a simulated robot",
            "cell",
            "cameras.driver",
            ((("cameras", "driver"), "oak"),),
        ),
        C(
            "simulated cameras on a real robot",
            "cell",
            "cameras.driver",
            ((("cameras", "driver"), "simulated"),),
            base="real",
        ),
        C(
            "reference camera unknown",
            "cell",
            "cameras.reference",
            ((("cameras", "reference"), "middle"),),
            base="real",
        ),
        C(
            "camera list missing",
            "cell",
            "cameras.list",
            ((("cameras", "list"), DELETE),),
            base="real",
        ),
        C("camera list empty", "cell", "cameras.list", ((("cameras", "list"), []),), base="real"),
        C(
            "camera without socket",
            "cell",
            "cameras.list[0].socket",
            ((("cameras", "list", 0, "socket"), DELETE),),
            base="real",
        ),
        C(
            "socket misspelt",
            "cell",
            "cameras.list[0].socket",
            ((("cameras", "list", 0, "socket"), "CAM_Z"),),
            base="real",
        ),
        C(
            "two cameras on one socket",
            "cell",
            "cameras.list",
            ((("cameras", "list", 1, "socket"), "CAM_B"),),
            base="real",
        ),
        C(
            "camera names twice",
            "cell",
            "cameras.list[1].name",
            ((("cameras", "list", 1, "name"), "left"),),
            base="real",
        ),
        C(
            "camera width zero",
            "cell",
            "cameras.list[0].width",
            ((("cameras", "list", 0, "width"), 0),),
            base="real",
        ),
        C(
            "camera height text",
            "cell",
            "cameras.list[0].height",
            ((("cameras", "list", 0, "height"), "800px"),),
            base="real",
        ),
        C(
            "camera width float",
            "cell",
            "cameras.list[0].width",
            ((("cameras", "list", 0, "width"), 1280.5),),
            base="real",
        ),
        C(
            "camera list on simulated cameras",
            "cell",
            "cameras.list",
            ((("cameras", "list"), [{"name": "cam", "width": 10, "height": 10}]),),
        ),
        C(
            "UVC option on an OAK",
            "cell",
            "cameras.list[0].fourcc",
            ((("cameras", "list", 0, "fourcc"), "MJPG"),),
            base="real",
        ),
        C("target missing", "cell", "target", ((("target",), DELETE),)),
        C("target kind unknown", "cell", "target.kind", ((("target", "kind"), "circles"),)),
        C(
            "square size in millimetres",
            "cell",
            "target.square_size_m",
            ((("target", "square_size_m"), 30),),
        ),
        C(
            "square size negative",
            "cell",
            "target.square_size_m",
            ((("target", "square_size_m"), -0.03),),
        ),
        C("square size zero", "cell", "target.square_size_m", ((("target", "square_size_m"), 0),)),
        C(
            "marker larger than square",
            "cell",
            "target.marker_size_m",
            ((("target", "marker_size_m"), 0.04),),
        ),
        C("squares_x float", "cell", "target.squares_x", ((("target", "squares_x"), 11.0),)),
        C("squares_y too few", "cell", "target.squares_y", ((("target", "squares_y"), 2),)),
        C("squares absurd", "cell", "target.squares_x", ((("target", "squares_x"), 100000),)),
        C(
            "dictionary unknown",
            "cell",
            "target.dictionary",
            ((("target", "dictionary"), "DICT_9X9_1"),),
        ),
        C(
            "board needs more markers than its dictionary",
            "cell",
            "target.dictionary",
            ((("target", "dictionary"), "DICT_4X4_50"), (("target", "squares_x"), 14)),
        ),
        C(
            "chessboard with marker size",
            "cell",
            "target.marker_size_m",
            ((("target", "kind"), "chessboard"),),
        ),
        C(
            "points target with 3 points",
            "cell",
            "target.points_m",
            ((("target",), {"kind": "points", "points_m": [[0, 0], [0.1, 0], [0, 0.1]]}),),
        ),
        C(
            "points target repeated",
            "cell",
            "target.points_m",
            ((("target",), {"kind": "points", "points_m": [[0, 0], [0, 0], [0.1, 0], [0, 0.1]]}),),
        ),
        C(
            "approximate target missing",
            "cell",
            "approximate.T_base_board",
            ((("approximate", "T_base_board"), DELETE),),
        ),
        C(
            "approximate of the other mount",
            "cell",
            "approximate.T_base_cam",
            ((("approximate", "T_base_cam"), {"rpy_deg": [0, 0, 0], "t_m": [0, 0, 1]}),),
        ),
        C(
            "approximate rotation not a rotation",
            "cell",
            "approximate.T_tool_cam.R",
            (
                (
                    ("approximate", "T_tool_cam"),
                    {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 2]], "t_m": [0, 0, 0]},
                ),
            ),
        ),
        C(
            "approximate R and rpy both",
            "cell",
            "approximate.T_tool_cam.rpy_deg",
            ((("approximate", "T_tool_cam", "R"), [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),),
        ),
        C(
            "approximate without rotation",
            "cell",
            "approximate.T_tool_cam.R",
            ((("approximate", "T_tool_cam", "rpy_deg"), DELETE),),
        ),
        C(
            "approximate t_m of 2",
            "cell",
            "approximate.T_base_board.t_m",
            ((("approximate", "T_base_board", "t_m"), [0.3, 0.1]),),
        ),
        C(
            "approximate rpy NaN",
            "cell",
            "approximate.T_base_board.rpy_deg",
            ((("approximate", "T_base_board", "rpy_deg"), [180, nan, 0]),),
        ),
        C(
            "standoff negative",
            "cell",
            "approximate.standoff_m",
            ((("approximate", "standoff_m"), -0.5),),
        ),
        C(
            "standoff in millimetres",
            "cell",
            "approximate.standoff_m",
            ((("approximate", "standoff_m"), 500),),
        ),
        C(
            "simulation truth missing",
            "cell",
            "simulation.T_tool_cam",
            ((("simulation", "T_tool_cam"), DELETE),),
        ),
        C(
            "simulation truth of the other mount",
            "cell",
            "simulation.T_tool_board",
            ((("simulation", "T_tool_board"), {"rpy_deg": [0, 0, 0], "t_m": [0, 0, 0]}),),
        ),
        C("simulation seed negative", "cell", "simulation.seed", ((("simulation", "seed"), -1),)),
        C(
            "simulation preset unknown",
            "cell",
            "simulation.camera_preset",
            ((("simulation", "camera_preset"), "r2"),),
        ),
        C(
            "simulated camera K not upper triangular",
            "cell",
            "simulation.cameras.cam.K",
            ((("simulation", "cameras", "cam", "K"), [[880, 0, 640], [1, 880, 400], [0, 0, 1]]),),
        ),
        C(
            "simulated camera K 2x2",
            "cell",
            "simulation.cameras.cam.K",
            ((("simulation", "cameras", "cam", "K"), [[880, 0], [0, 880]]),),
        ),
        C(
            "simulated camera distortion of 4",
            "cell",
            "simulation.cameras.cam.distortion",
            ((("simulation", "cameras", "cam", "distortion"), [0, 0, 0, 0]),),
        ),
        C(
            "simulated camera key typo",
            "cell",
            "simulation.cameras.cam.noise_sdt",
            ((("simulation", "cameras", "cam", "noise_sdt"), 2.0),),
        ),
        C(
            "new simulated camera without K",
            "cell",
            "simulation.cameras.extra.K",
            ((("simulation", "cameras", "extra"), {"width": 640, "height": 480}),),
        ),
        C(
            "simulated blur negative",
            "cell",
            "simulation.cameras.cam.blur_sigma_px",
            ((("simulation", "cameras", "cam", "blur_sigma_px"), -1.0),),
        ),
        C(
            "rig names an unknown camera",
            "cell",
            "simulation.rig.ghost",
            ((("simulation", "rig", "ghost"), {"rpy_deg": [0, 0, 0], "t_m": [0.07, 0, 0]}),),
        ),
        C(
            "noise negative",
            "cell",
            "simulation.noise.robot_mm",
            ((("simulation", "noise", "robot_mm"), -0.05),),
        ),
        C(
            "jitter as text",
            "cell",
            "simulation.target_jitter.mm",
            ((("simulation", "target_jitter", "mm"), "two"),),
        ),
        C(
            "plan key that did nothing: tilt_deg",
            "cell",
            "plan.tilt_deg",
            ((("plan", "tilt_deg"), 25),),
        ),
        C(
            "plan key that did nothing: frames_per_group",
            "cell",
            "plan.frames_per_group",
            ((("plan", "frames_per_group"), 5),),
        ),
        C("plan key that did nothing: groups", "cell", "plan.groups", ((("plan", "groups"), 4),)),
        C(
            "plan tilt beyond the detector",
            "cell",
            "plan.tilts_deg",
            ((("plan", "tilts_deg"), [60]),),
        ),
        C("plan tilts not a list", "cell", "plan.tilts_deg", ((("plan", "tilts_deg"), 25),)),
        C("plan step negative", "cell", "plan.step_mm", ((("plan", "step_mm"), [-40]),)),
        C(
            "plan goal typo",
            "cell",
            "plan.goal.fx_rel_sdt",
            ((("plan", "goal"), {"fx_rel_sdt": 1e-3}),),
        ),
        C(
            "plan goal negative",
            "cell",
            "plan.goal.fx_rel_std",
            ((("plan", "goal"), {"fx_rel_std": -1e-3}),),
        ),
        C("plan is a list", "cell", "plan", ((("plan",), [1, 2]),)),
        C(
            "options distortion of 4",
            "cell",
            "options.distortion",
            ((("options", "distortion"), [True, True, True, True]),),
        ),
        C(
            "options distortion as numbers",
            "cell",
            "options.distortion",
            ((("options", "distortion"), [1, 1, 1, 1, 0]),),
        ),
        C("options skew as text", "cell", "options.skew", ((("options", "skew"), "no"),)),
        C(
            "options robot noise negative",
            "cell",
            "options.robot_noise_mm",
            ((("options", "robot_noise_mm"), -0.05),),
        ),
        C(
            "options robot noise NaN",
            "cell",
            "options.robot_noise_deg",
            ((("options", "robot_noise_deg"), nan),),
        ),
        C(
            "options outlier threshold zero",
            "cell",
            "options.outlier_threshold_px",
            ((("options", "outlier_threshold_px"), 0),),
        ),
        # -- plan files
        C("plan format missing", "plan", "format", ((("format",), DELETE),)),
        C("plan format wrong", "plan", "format", ((("format",), "slidecal.plan/9"),)),
        C("plan without groups", "plan", "groups", ((("groups",), DELETE),)),
        C("plan groups empty", "plan", "groups", ((("groups",), []),)),
        C("plan group empty", "plan", "groups[1]", ((("groups", 1), []),)),
        C("plan group is a pose", "plan", "groups[0]", ((("groups", 0), _POSE),)),
        C("plan pose of 7 numbers", "plan", "groups[0][1]", ((("groups", 0, 1), [*_POSE, 0.0]),)),
        C(
            "plan pose with null",
            "plan",
            "groups[2][0]",
            ((("groups", 2, 0), [0, 0, None, 0, 0, 0]),),
        ),
        C(
            "plan pose NaN",
            "plan",
            "groups[0][0]",
            ((("groups", 0, 0), [nan, 0, 0.5, 3.14, 0, 0]),),
        ),
        C(
            "plan pose in millimetres",
            "plan",
            "groups[0][0]",
            ((("groups", 0, 0), [-400.0, 0.0, 545.0, 3.14, 0.0, 0.0]),),
        ),
        C(
            "plan rotations in degrees inside a group",
            "plan",
            "groups[1][1]",
            ((("groups", 1, 1), [-0.38, 0.0, 0.545, 180.0, 0.0, 0.0]),),
        ),
        C(
            "plan group that rotates",
            "plan",
            "groups[0][1]",
            ((("groups", 0, 1), [-0.38, 0.0, 0.545, 3.14159265, 0.1, 0.0]),),
        ),
        C("plan via of 3 numbers", "plan", "via", ((("via",), [0, 0, 0.5]),)),
        C("plan speed zero", "plan", "speed_mps", ((("speed_mps",), 0),)),
        C("plan speed too high", "plan", "speed_mps", ((("speed_mps",), 5.0),)),
        C("plan accel text", "plan", "accel_mps2", ((("accel_mps2",), "1 m/s2"),)),
        C("plan settle negative", "plan", "settle_s", ((("settle_s",), -1),)),
        C(
            "plan predicted std not a mapping",
            "plan",
            "predicted_std",
            ((("predicted_std",), [0.3]),),
        ),
        C(
            "plan predicted std text",
            "plan",
            "predicted_std.cam.fx_px",
            ((("predicted_std", "cam.fx_px"), "small"),),
        ),
        C("plan duration negative", "plan", "duration_s", ((("duration_s",), -3),)),
        C("plan notes not text", "plan", "notes[0]", ((("notes",), [{"a": 1}]),)),
        # -- session files
        C("session format missing", "session", "format", ((("format",), DELETE),)),
        C(
            "session format of a newer slidecal",
            "session",
            "format",
            ((("format",), "slidecal.session/2"),),
        ),
        C("session status unknown", "session", "status", ((("status",), "done"),)),
        C("session knowledge unknown", "session", "knowledge", ((("knowledge",), "robots"),)),
        C("session mount unknown", "session", "mount", ((("mount",), "on_the_wall"),)),
        C("session cameras empty", "session", "cameras", ((("cameras",), []),)),
        C("session cameras not a list", "session", "cameras", ((("cameras",), {"cam": 1}),)),
        C(
            "session camera width negative",
            "session",
            "cameras[0].width",
            ((("cameras", 0, "width"), -5),),
        ),
        C(
            "session camera socket wrong",
            "session",
            "cameras[0].socket",
            ((("cameras", 0, "socket"), "B"),),
        ),
        C(
            "session reference unknown",
            "session",
            "reference_camera",
            ((("reference_camera",), "left"),),
        ),
        C("session target missing", "session", "target", ((("target",), DELETE),)),
        C(
            "session target typo",
            "session",
            "target.square_size",
            ((("target", "square_size"), 0.03),),
        ),
        C("session frames missing", "session", "frames", ((("frames",), DELETE),)),
        C("session frames a mapping", "session", "frames", ((("frames",), {"0": {}}),)),
        C("session frame id negative", "session", "frames[0].id", ((("frames", 0, "id"), -1),)),
        C("session frame id twice", "session", "frames[1].id", ((("frames", 1, "id"), 0),)),
        C("session frame id text", "session", "frames[1].id", ((("frames", 1, "id"), "one"),)),
        C(
            "session pose of 5",
            "session",
            "frames[0].T_base_tool",
            ((("frames", 0, "T_base_tool"), _POSE[:5]),),
        ),
        C(
            "session pose inf",
            "session",
            "frames[1].T_base_tool",
            ((("frames", 1, "T_base_tool"), [inf, 0, 0, 0, 0, 0]),),
        ),
        C(
            "session pose quaternion not unit",
            "session",
            "frames[0].T_base_tool.q_wxyz",
            (
                (
                    ("frames", 0, "T_base_tool"),
                    {"q_wxyz": [0.5, 0.5, 0.5, 0.6], "t_mm": [400, 0, 300]},
                ),
            ),
        ),
        C(
            "session pose transform in mm given as t_m",
            "session",
            "frames[0].T_base_tool.t_m",
            ((("frames", 0, "T_base_tool"), {"rpy_deg": [180, 0, 0], "t_m": [400, 0, 300]}),),
        ),
        C(
            "session pose quaternion and angles",
            "session",
            "frames[0].T_base_tool.q_wxyz",
            (
                (
                    ("frames", 0, "T_base_tool"),
                    {"q_wxyz": [1, 0, 0, 0], "rpy_deg": [0, 0, 0], "t_mm": [400, 0, 300]},
                ),
            ),
        ),
        C(
            "session pose on one frame only",
            "session",
            "frames[1].T_base_tool",
            ((("frames", 1, "T_base_tool"), DELETE),),
        ),
        C("session group negative", "session", "frames[0].group", ((("frames", 0, "group"), -2),)),
        C(
            "session motion of 2",
            "session",
            "frames[0].motion_board",
            ((("frames", 0, "motion_board"), [0, 1]),),
        ),
        C(
            "session detections of an unknown camera",
            "session",
            "frames[0].detections.left",
            ((("frames", 0, "detections", "left"), {"ids": [], "px": []}),),
        ),
        C(
            "session ids off the board",
            "session",
            "frames[0].detections.cam.ids",
            ((("frames", 0, "detections", "cam", "ids"), [0, 1, 70]),),
        ),
        C(
            "session ids negative",
            "session",
            "frames[0].detections.cam.ids",
            ((("frames", 0, "detections", "cam", "ids"), [0, -1, 2]),),
        ),
        C(
            "session ids repeated",
            "session",
            "frames[0].detections.cam.ids",
            ((("frames", 0, "detections", "cam", "ids"), [0, 1, 1]),),
        ),
        C(
            "session ids floats",
            "session",
            "frames[0].detections.cam.ids",
            ((("frames", 0, "detections", "cam", "ids"), [0.0, 1.0, 2.0]),),
        ),
        C(
            "session px count",
            "session",
            "frames[0].detections.cam.px",
            ((("frames", 0, "detections", "cam", "px"), [[1.0, 2.0]]),),
        ),
        C(
            "session px of 3 columns",
            "session",
            "frames[0].detections.cam.px",
            ((("frames", 0, "detections", "cam", "px"), [[1, 2, 3], [1, 2, 3], [1, 2, 3]]),),
        ),
        C(
            "session px NaN",
            "session",
            "frames[1].detections.cam.px",
            ((("frames", 1, "detections", "cam", "px"), [[nan, 1.0], [1.0, 1.0], [2.0, 1.0]]),),
        ),
        C(
            "session px outside the image",
            "session",
            "frames[1].detections.cam.px",
            (
                (
                    ("frames", 1, "detections", "cam", "px"),
                    [[100.0, 100.0], [1500.0, 90.0], [2.0, 1.0]],
                ),
            ),
        ),
        C(
            "session image that does not exist",
            "session",
            "frames[0].images.cam",
            (
                (("frames", 0, "images"), {"cam": "images/0000_cam.png"}),
                (("frames", 0, "detections"), DELETE),
            ),
        ),
        C(
            "session image outside the session",
            "session",
            "frames[0].images.cam",
            ((("frames", 0, "images"), {"cam": "../../etc/passwd"}),),
        ),
        C(
            "session image path a number",
            "session",
            "frames[0].images.cam",
            ((("frames", 0, "images"), {"cam": 7}),),
        ),
        C(
            "session quality of an unknown camera",
            "session",
            "frames[0].quality.left",
            ((("frames", 0, "quality"), {"left": {"ok": True}}),),
        ),
        C("session options typo", "session", "options.skeww", ((("options", "skeww"), True),)),
        C(
            "session robot knowledge without poses",
            "session",
            "knowledge",
            ((("frames", 0, "T_base_tool"), DELETE), (("frames", 1, "T_base_tool"), DELETE)),
        ),
        C("session events not a list", "session", "events", ((("events",), "none"),)),
        C(
            "session event without message",
            "session",
            "events[0].message",
            ((("events",), [{"kind": "fault"}]),),
        ),
        C(
            "session truth rotation wrong",
            "session",
            "simulation.T_tool_cam.R",
            (
                (
                    ("simulation",),
                    {"T_tool_cam": {"R": [[2, 0, 0], [0, 1, 0], [0, 0, 1]], "t_m": [0, 0, 0]}},
                ),
            ),
        ),
        C("session truth typo", "session", "simulation.sed", ((("simulation",), {"sed": 3}),)),
        C(
            "session truth camera K shape",
            "session",
            "simulation.cameras.cam.K",
            ((("simulation",), {"cameras": {"cam": {"K": [1, 2, 3], "distortion": [0] * 5}}}),),
        ),
        C("session cell hash not hex", "session", "cell_sha256", ((("cell_sha256",), "abc"),)),
        # -- result files
        C("result format wrong", "result", "format", ((("format",), "slidecal.session/1"),)),
        C("result without cameras", "result", "cameras", ((("cameras",), DELETE),)),
        C("result cameras empty", "result", "cameras", ((("cameras",), {}),)),
        C(
            "result K 3x2",
            "result",
            "cameras.cam.K",
            ((("cameras", "cam", "K"), [[1, 0], [0, 1], [0, 0]]),),
        ),
        C(
            "result distortion NaN",
            "result",
            "cameras.cam.distortion",
            ((("cameras", "cam", "distortion"), [nan, 0, 0, 0, 0]),),
        ),
        C(
            "result distortion model unknown",
            "result",
            "cameras.cam.distortion_model",
            ((("cameras", "cam", "distortion_model"), "fisheye"),),
        ),
        C(
            "result std negative",
            "result",
            "cameras.cam.std.fx",
            ((("cameras", "cam", "std", "fx"), -0.2),),
        ),
        C(
            "result width text",
            "result",
            "cameras.cam.width",
            ((("cameras", "cam", "width"), "wide"),),
        ),
        C(
            "result hand-eye R not a rotation",
            "result",
            "T_tool_cam.R",
            ((("T_tool_cam", "R"), [[1, 0, 0], [0, 1, 0], [0, 0, -1]]),),
        ),
        C(
            "result hand-eye t of 2",
            "result",
            "T_tool_cam.t_m",
            ((("T_tool_cam", "t_m"), [0.0, 0.1]),),
        ),
        C(
            "result std_t_mm text",
            "result",
            "T_tool_cam.std_t_mm",
            ((("T_tool_cam", "std_t_mm"), "0.1 mm"),),
        ),
        C("result mount unknown", "result", "mount", ((("mount",), "ceiling"),)),
        C(
            "result reference unknown",
            "result",
            "reference_camera",
            ((("reference_camera",), "left"),),
        ),
        C("result converged text", "result", "converged", ((("converged",), "yes"),)),
        C("result iterations negative", "result", "iterations", ((("iterations",), -1),)),
        C(
            "result per-image camera unknown",
            "result",
            "reprojection.per_image[0].camera",
            ((("reprojection", "per_image", 0, "camera"), "left"),),
        ),
        C(
            "result per-image rms negative",
            "result",
            "reprojection.per_image[0].rms_px",
            ((("reprojection", "per_image", 0, "rms_px"), -1.0),),
        ),
        C("result covariance wrong size", "result", "covariance", ((("covariance",), [[1.0]]),)),
        C(
            "result covariance not symmetric",
            "result",
            "covariance",
            ((("covariance",), [[1.0, 0.5], [0.0, 1.0]]),),
        ),
        C(
            "result parameter names not text",
            "result",
            "parameter_names[1]",
            ((("parameter_names",), ["cam.fx", 2]),),
        ),
        C("result outlier malformed", "result", "outliers[0]", ((("outliers",), [[0, "cam"]]),)),
        C(
            "result unobservable reason a number",
            "result",
            "unobservable.T_tool_cam.t_m",
            ((("unobservable",), {"T_tool_cam.t_m": 3}),),
        ),
        C(
            "result scale check typo",
            "result",
            "scale_checks[0].robot_m",
            ((("scale_checks", 0, "robot_m"), 50.0),),
        ),
        C(
            "result H_inf badly named",
            "result",
            "H_inf.cam",
            ((("H_inf",), {"cam": [[1, 0, 0]] * 3}),),
        ),
        C(
            "result linear of unknown camera",
            "result",
            "linear.left",
            ((("linear",), {"left": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}),),
        ),
        C("result messages not text", "result", "messages[0]", ((("messages",), [{"a": 1}]),)),
    ]
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
    from slidecal.routines import cli

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
    """``docs/BAD_INPUT.md``: every case and the line slidecal answers it with."""
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
        "Generated by `python -m slidecal.routines.bad_input docs/BAD_INPUT.md` (do not edit by",
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


def main(argv: list[str] | None = None) -> int:
    """``python -m slidecal.routines.bad_input [OUT.md]``: write (or print) the table."""
    argv = sys.argv[1:] if argv is None else argv
    text = table_markdown()
    if argv:
        Path(argv[0]).write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

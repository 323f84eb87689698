"""The command line: exit codes, one-line messages, solve on a recorded fixture."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from slidecal.routines import cli
from slidecal.solver.errors import HardwareFault

DATA = Path(__file__).parent / "data"


def _slidecal(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "slidecal.routines.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_missing_session_is_one_line_exit_2(tmp_path: Path) -> None:
    p = _slidecal("solve", str(tmp_path / "nope"), cwd=tmp_path)
    assert p.returncode == 2
    assert p.stderr.startswith("slidecal: ") and p.stderr.count("\n") == 1
    assert "Traceback" not in p.stderr


def test_bad_cell_file_is_one_line_exit_2_and_writes_nothing(tmp_path: Path) -> None:
    cell = tmp_path / "cell.yaml"
    cell.write_text("robot: {driver: ur}\ntarget: {kind: charuco}\n")
    p = _slidecal("run", "--config", str(cell), "--out", str(tmp_path / "s"), cwd=tmp_path)
    assert p.returncode == 2 and p.stderr.count("\n") == 1
    assert "cell.yaml: robot.host" in p.stderr and "controller's address" in p.stderr
    assert not (tmp_path / "s").exists()


def test_solve_recorded_fixture(tmp_path: Path) -> None:
    shutil.copytree(DATA / "r1_session", tmp_path / "s")
    p = _slidecal("solve", str(tmp_path / "s"), "--out", str(tmp_path / "r.yaml"), cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    r = yaml.safe_load((tmp_path / "r.yaml").read_text())
    truth = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())["simulation"]
    fx, fx_true = r["cameras"]["cam"]["K"][0][0], truth["cameras"]["cam"]["K"][0][0]
    assert abs(fx - fx_true) / fx_true < 1e-3
    assert "errors against the simulated truth" in p.stdout


def test_hardware_fault_exit_3(monkeypatch, capsys) -> None:
    import slidecal.routines.run as run

    def boom(*a, **k):
        raise HardwareFault("protective stop during move 3;\n unlock it on the pendant")

    monkeypatch.setattr(run, "run_calibration", boom)
    assert cli.main(["run", "--quiet"]) == 3
    err = capsys.readouterr().err
    assert err == "slidecal: protective stop during move 3; unlock it on the pendant\n"


def test_subcommands_are_a_table() -> None:
    assert {"run", "solve"} <= set(cli.SUBCOMMANDS)
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["nothing"])


def test_unattended_subcommands_registered() -> None:
    assert {"check", "rollback"} <= set(cli.SUBCOMMANDS)
    p = cli.build_parser()
    assert p.parse_args(["check", "--installed", "s"]).installed == "s"
    assert p.parse_args(["rollback", "s"]).store == "s"


def test_solve_rejected_exit_4_and_rollback_cli(tmp_path: Path, capsys) -> None:
    from slidecal.routines.ops.install import install, installed_result
    from slidecal.routines.solve import solve_session

    shutil.copytree(DATA / "r1_session", tmp_path / "s")
    good = solve_session(tmp_path / "s")
    store = tmp_path / "store"
    first = install(store, tmp_path / "s", good.result, "accepted")
    install(store, tmp_path / "s", good.result, "accepted")
    assert cli.main(["rollback", str(store)]) == 0
    assert first.name in capsys.readouterr().out
    assert (store / "current").resolve() == first and installed_result(store) is not None
    # a session whose board is given as 0.025 m squares instead of 0.030 m: rejected, exit 4,
    # nothing installed
    doc = yaml.safe_load((tmp_path / "s" / "session.yaml").read_text())
    t = doc["target"]
    t["marker_size_m"] = t["marker_size_m"] * 0.025 / t["square_size_m"]
    t["square_size_m"] = 0.025
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "session.yaml").write_text(yaml.safe_dump(doc))
    assert cli.main(["solve", str(tmp_path / "d"), "--quiet", "--installed", str(store)]) == 4
    assert capsys.readouterr().out.startswith("verdict: rejected")
    assert (tmp_path / "d" / "rejected" / "result.yaml").is_file()
    assert cli.main(["rollback", str(store)]) == 2  # nothing before the first install


def test_session_of_photographs_with_a_wrong_dictionary_names_the_right_one(tmp_path: Path) -> None:
    # a user's mistake on real photographs (data/opencv_charuco): the board's markers are
    # DICT_6X6_250, the session says the default DICT_5X5_100; the refusal says what is in view
    s = tmp_path / "s"
    (s / "images").mkdir(parents=True)
    for k in range(3):
        shutil.copy(DATA / "opencv_charuco" / "choriginal.jpg", s / "images" / f"{k}.jpg")
    session = {
        "format": "slidecal.session/1",
        "target": {
            "kind": "charuco",
            "squares_x": 5,
            "squares_y": 7,
            "square_size_m": 0.04,
            "marker_size_m": 0.02,
        },
        "cameras": [{"name": "cam", "width": 640, "height": 480}],
        "frames": [{"id": k, "images": {"cam": f"images/{k}.jpg"}} for k in range(3)],
    }
    (s / "session.yaml").write_text(yaml.safe_dump(session))
    p = _slidecal("solve", str(s), "--out", str(tmp_path / "r.yaml"), cwd=tmp_path)
    assert p.returncode != 0 and p.stderr.count("\n") == 1 and "Traceback" not in p.stderr
    assert "no ArUco marker of DICT_5X5_100 found" in p.stderr
    assert "set target.dictionary to DICT_6X6_50" in p.stderr
    assert not (tmp_path / "r.yaml").exists()


def test_solve_config_misspelt_limits_is_refused(tmp_path: Path, capsys) -> None:
    """`solve --config` reads only the cell's limits:, but a misspelt section is not ignored."""
    cell = tmp_path / "cell.yaml"
    cell.write_text("limts: {fx_rel_std: 0.01}\n")
    code = cli.main(["solve", str(DATA / "r1_session"), "--quiet", "--config", str(cell)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    assert "cell.yaml: limts" in err and "did you mean limits" in err


def test_version(capsys) -> None:
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("slidecal ")

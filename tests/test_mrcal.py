"""slidecal's ``.cameramodel`` exports read by the real mrcal (skipped where mrcal is not
installed: ``pip install --no-deps mrcal numpysane gnuplotlib shapely``, CPython 3.12 and newer;
CI runs it on its newest Python)."""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from slidecal.mocks import scenarios as sc
from slidecal.mocks.camera import LENSES
from slidecal.routines.exports import VALID_REGION_PX, mrcal_cameramodel
from slidecal.solver.calibrate import calibrate
from slidecal.solver.camera import project
from slidecal.solver.problem import ModelOptions

mrcal = pytest.importorskip("mrcal")


def _solved(model: str, k3: bool = True):  # noqa: ANN202
    opts = ModelOptions(distortion_model=model, distortion=(True,) * 4 + (k3,))
    dist = LENSES[model] if k3 else np.r_[LENSES[model][:4], 0.0]
    s = sc.r1(np.random.default_rng(5), 0.15, 0.0, 0.0, options=opts, dist=dist)
    return calibrate(s.problem)


@pytest.mark.parametrize(
    ("model", "k3", "lensmodel"),
    [
        ("opencv5", False, "LENSMODEL_OPENCV4"),
        ("opencv5", True, "LENSMODEL_OPENCV5"),
        ("rational", True, "LENSMODEL_OPENCV8"),
    ],
)
def test_mrcal_reads_and_projects_the_export(model, k3, lensmodel, tmp_path) -> None:
    res = _solved(model, k3)
    cam = res.cameras["cam"]
    path = tmp_path / "cam.cameramodel"
    path.write_text(mrcal_cameramodel(res, "cam"))
    m = mrcal.cameramodel(str(path))
    assert m.intrinsics()[0] == lensmodel
    P = np.column_stack([np.random.default_rng(2).uniform(-0.4, 0.4, (40, 2)), np.ones(40)])
    np.testing.assert_allclose(
        mrcal.project(P, *m.intrinsics()), project(cam.K, cam.distortion, P), atol=1e-9
    )
    region = m.valid_intrinsics_region()
    assert region is not None and np.array_equal(region[0], region[-1])
    assert np.all((region >= 0) & (region <= [cam.width - 1, cam.height - 1]))
    if lensmodel == "LENSMODEL_OPENCV4":  # mrcal's own Kalibr converter takes it
        tool = shutil.which("mrcal-to-kalibr", path=str(Path(sys.executable).parent))
        if tool is not None:
            out = subprocess.run([tool, str(path)], capture_output=True, text=True, check=True)
            assert "radtan" in out.stdout


def test_valid_region_is_where_the_uncertainty_is_below_the_level(tmp_path) -> None:
    """Scaling the covariance up shrinks the region; past the level everywhere: no region."""
    res = _solved("opencv5", k3=False)
    areas = []
    for scale in (1.0, 1e4, 1e8):
        r = dataclasses.replace(res, covariance=np.asarray(res.covariance) * scale)
        path = tmp_path / f"{scale}.cameramodel"
        path.write_text(mrcal_cameramodel(r, "cam"))
        region = mrcal.cameramodel(str(path)).valid_intrinsics_region()
        x, y = (region.T if region is not None else np.zeros((2, 1)))
        areas.append(0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))
    assert areas[0] >= areas[1] >= areas[2] and areas[2] == 0.0 and VALID_REGION_PX == 1.0

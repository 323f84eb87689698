"""Benchmark S5 (docs/SETUPS.md; Malm and Heyden 2006, Figs. 7-9): stereo head, general motion.

Each camera calibrated alone (Zhang, eqs. 10-11) against both cameras calibrated jointly with
the infinite homography (eqs. 58-62), over noise levels sigma = 0.1 ... 0.8 px, then with the
left camera at twice the right's noise. Camera ``a`` is the left camera, ``b`` the right one
(``X_left = R_left_right X_right + t_left_right``).

Regenerate the figures and the table of ``docs/results/S5.md``::

    python -m tests.bench stereo
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from slidecal.mocks.scenarios import (
    PAPER_SIZE_PX,
    StereoScene,
    s5_scene,
)
from slidecal.solver.errors import InputError
from slidecal.solver.geometry import rotation_angle_deg
from slidecal.solver.stereo import infinite_homography, rig_linear_intrinsics
from tests.bench.report import RESULTS, report_header
from tests.helpers import relative_rotation
from tests.linear_scenes import estimate_homographies, params_of

PARAMS = ("fx", "fy", "cx", "cy")
SIGMAS_PX = tuple(np.round(np.arange(0.1, 0.81, 0.1), 2))


def run_trial(
    scene: StereoScene,
    sigma_left_px: float,
    sigma_right_px: float,
    rng: np.random.Generator,
    skew: bool = True,
) -> dict[str, np.ndarray]:
    """One Monte-Carlo trial: noisy points, homographies, separate and joint calibration.

    Returns (fx, fy, cx, cy) estimates (4,) under keys ``sep_left``, ``sep_right``,
    ``joint_left``, ``joint_right``, and ``rot_err_deg`` (1,): the joint ``R_left_right`` error.
    """
    px_l, px_r = scene.pixels()
    px_l = px_l + rng.normal(scale=sigma_left_px, size=px_l.shape)
    px_r = px_r + rng.normal(scale=sigma_right_px, size=px_r.shape)
    H_l = estimate_homographies(scene.board_xy, px_l)
    H_r = estimate_homographies(scene.board_xy, px_r)
    sizes = (PAPER_SIZE_PX, PAPER_SIZE_PX)
    Ks_l, Ks_r = rig_linear_intrinsics(H_l, H_r, None, skew=skew, sizes=sizes)
    H_inf, _ = infinite_homography(H_l, H_r, sizes=sizes)
    Kj_l, Kj_r = rig_linear_intrinsics(H_l, H_r, H_inf, skew=skew, sizes=sizes)
    R = relative_rotation(Kj_l, Kj_r, H_inf)
    return {
        "sep_left": params_of(Ks_l),
        "sep_right": params_of(Ks_r),
        "joint_left": params_of(Kj_l),
        "joint_right": params_of(Kj_r),
        "rot_err_deg": np.array([rotation_angle_deg(R, scene.R_left_right)]),
    }


def sweep(
    scene: StereoScene, left_factor: float, trials: int, seed: int
) -> dict[str, np.ndarray]:
    """Mean relative errors over ``trials`` per noise level (right sigma in ``SIGMAS_PX``).

    Returns arrays (len(SIGMAS_PX), 4) of mean |relative error| of (fx, fy, cx, cy) for each
    key of :func:`run_trial`, and ``rot_err_deg`` (len(SIGMAS_PX),) mean rotation error.
    """
    truth = {"left": params_of(scene.K_left), "right": params_of(scene.K_right)}
    out: dict[str, list] = {k: [] for k in ("sep_left", "sep_right", "joint_left", "joint_right")}
    out["rot_err_deg"] = []
    for i, sigma in enumerate(SIGMAS_PX):
        rng = np.random.default_rng([seed, i])
        acc: dict[str, list] = {k: [] for k in out}
        for _ in range(trials):
            res = run_trial(scene, left_factor * sigma, sigma, rng)
            for k, v in res.items():
                if k == "rot_err_deg":
                    acc[k].append(v[0])
                else:
                    cam = k.split("_")[1]
                    acc[k].append(np.abs(v - truth[cam]) / truth[cam])
        for k in out:
            out[k].append(np.mean(acc[k], axis=0))
    return {k: np.array(v) for k, v in out.items()}


def _plot(res: dict[str, np.ndarray], cam: str, factor: float, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sig = np.array(SIGMAS_PX) * factor
    fig, ax = plt.subplots(figsize=(5.0, 3.6))
    ax.plot(sig, 100 * res[f"sep_{cam}"][:, 0], "k--o", ms=3, label="alone (eqs. 10-11)")
    ax.plot(sig, 100 * res[f"joint_{cam}"][:, 0], "k-s", ms=3, label="joint (eqs. 10-11, 62)")
    ax.set_xlabel(f"noise sigma, {cam} camera (px)")
    ax.set_ylabel("mean relative error of fx (%)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _table(res: dict[str, np.ndarray], factor: float) -> list[str]:
    lines = [
        "| sigma right (px) | sigma left (px) | camera | "
        + " | ".join(f"{p} alone / joint (%) | ratio" for p in PARAMS)
        + " |",
        "| " + " | ".join(["---"] * (3 + 2 * len(PARAMS))) + " |",
    ]
    for i, sigma in enumerate(SIGMAS_PX):
        for cam in ("left", "right"):
            cells = []
            for j in range(len(PARAMS)):
                s, jn = res[f"sep_{cam}"][i, j], res[f"joint_{cam}"][i, j]
                cells += [f"{100 * s:.3f} / {100 * jn:.3f}", f"{jn / s:.2f}"]
            lines.append(
                f"| {sigma:.1f} | {factor * sigma:.1f} | {cam} | " + " | ".join(cells) + " |"
            )
    return lines


def _summary(res: dict[str, np.ndarray]) -> list[str]:
    lines = []
    for cam in ("left", "right"):
        r = res[f"joint_{cam}"] / res[f"sep_{cam}"]
        mean = ", ".join(f"{p} {m:.2f}" for p, m in zip(PARAMS, r.mean(axis=0), strict=True))
        lines.append(f"- {cam} camera, joint / alone averaged over the noise levels: {mean}")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Run S5 and write ``s5_*.png`` and ``S5.md`` into ``--out``."""
    ap = argparse.ArgumentParser(
        prog="python -m tests.bench stereo", description=__doc__.splitlines()[0]
    )
    ap.add_argument("--out", type=Path, default=RESULTS, help="the folder of S5.md and its figures")
    ap.add_argument("--trials", type=int, default=100)
    ap.add_argument("--seed", type=int, default=20060401)
    args = ap.parse_args(argv)
    try:  # checked before the sweeps, not after them
        import matplotlib  # noqa: F401
    except ImportError as e:
        raise InputError(
            "python -m tests.bench stereo draws its figures with matplotlib, which is not "
            f"installed ({e}); install it with pip install 'slidecal[bench]'"
        ) from None
    args.out.mkdir(parents=True, exist_ok=True)
    scene = s5_scene()
    t0 = time.perf_counter()
    equal = sweep(scene, 1.0, args.trials, args.seed)
    double = sweep(scene, 2.0, args.trials, args.seed + 1)
    elapsed_s = time.perf_counter() - t0
    _plot(equal, "left", 1.0, "S5 / Fig. 7: left camera, equal noise", args.out / "s5_fig7.png")
    _plot(equal, "right", 1.0, "S5 / Fig. 8: right camera, equal noise", args.out / "s5_fig8.png")
    _plot(double, "left", 2.0, "S5 / Fig. 9: left camera at twice the noise",
          args.out / "s5_fig9.png")
    _plot(double, "right", 1.0, "S5: right camera when the left has twice the noise",
          args.out / "s5_fig9_right.png")
    text = _report(equal, double, args.trials, args.seed, elapsed_s, argv)
    (args.out / "S5.md").write_text(text)
    print(text)
    return 0


def _report(equal, double, trials: int, seed: int, elapsed_s: float, argv) -> str:
    rot = ", ".join(f"{s:.1f}: {e:.3f}" for s, e in zip(SIGMAS_PX, equal["rot_err_deg"],
                                                         strict=True))
    return "\n".join(
        [
            *report_header(
                "S5: stereo head, each camera alone against joint calibration with eq. 62",
                "stereo", argv, elapsed_s,
            ),
            f"{trials} trials per noise level, seed {seed}.",
            "",
            "This is the linear part. The maximum-likelihood refinement of the same set-up "
            "(both cameras, the rig and every board pose, through `calibrate`) against its "
            "Cramer-Rao bound is in docs/results/RIG.md (`python -m tests.bench rig`).",
            "",
            "## Summary",
            "",
            "Equal noise on both cameras (Figs. 7, 8):",
            "",
            *_summary(equal),
            "",
            "Left camera at twice the right camera's noise (Fig. 9):",
            "",
            *_summary(double),
            "",
            f"Mean error of the joint `R_left_right` (deg) by sigma: {rot}.",
            "",
            "## Equal noise",
            "",
            *_table(equal, 1.0),
            "",
            "## Left camera at twice the noise",
            "",
            *_table(double, 2.0),
            "",
        ]
    )


if __name__ == "__main__":
    raise SystemExit(main())

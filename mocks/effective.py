"""What a simulated session can know of its truth: the hand-eye and target pose moved by the arm's
constant error; apart from the simulator, so that judging a result imports none of it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from slidecal.solver.errors import InputError
from slidecal.solver.geometry import R_from_rvec, T_from_Rt, inv_T, rvec_from_R
from slidecal.solver.numeric import least_squares


def effective_truth(
    mount: str,
    T_base_tool_true: Sequence[np.ndarray],
    T_base_tool_measured: Sequence[np.ndarray],
    T_hand_eye: np.ndarray,
    T_target: np.ndarray,
    sigma_rot_deg: float = 0.1,
    sigma_mm: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The hand-eye and target pose ``(T_hand_eye, T_target)`` as a session can know them.

    ``mount`` names the physical truth ``T_hand_eye``, ``T_target`` of the reference camera;
    ``T_base_tool_true`` / ``_measured`` (4, 4) per frame. The arm's constant error is
    indistinguishable from a change of both, so the solver's zero-mean pose corrections converge to
    ``X' = B X``, ``Y' = Y A`` (``X`` the inverse hand-eye, ``Y`` the target pose) minimising
    ``sum_k |rot(E_k)|^2 / sigma_rot^2 + |t(E_k)|^2 / sigma_t^2`` over the corrections ``E_k``.
    """
    T_true = [np.asarray(T, dtype=float) for T in T_base_tool_true]
    T_meas = [np.asarray(T, dtype=float) for T in T_base_tool_measured]
    if len(T_true) != len(T_meas):
        raise InputError(
            f"{len(T_true)} true robot poses for {len(T_meas)} measured ones; give one per frame"
        )
    eih = mount == "eye_in_hand"
    X, Y = inv_T(np.asarray(T_hand_eye, float)), np.asarray(T_target, float)
    w = np.array([1.0 / np.radians(sigma_rot_deg)] * 3 + [1000.0 / sigma_mm] * 3)

    def corrections(p: np.ndarray) -> np.ndarray:
        A = T_from_Rt(R_from_rvec(p[:3]), p[3:6])
        B = T_from_Rt(R_from_rvec(p[6:9]), p[9:12])
        out = []
        for Tt, Tm in zip(T_true, T_meas, strict=True):
            # the pose the camera saw with the model's X' = B X, Y' = Y A (eye-in-hand:
            # X' (T)^-1 Y' = X Tt^-1 Y, so T = Y' Y^-1 Tt X^-1 X'); eye-to-hand alike
            if eih:
                T = (Y @ A) @ inv_T(Y) @ Tt @ inv_T(X) @ (B @ X)
            else:
                T = inv_T(B @ X) @ X @ Tt @ Y @ inv_T(Y @ A)
            E_rot = rvec_from_R(T[:3, :3] @ Tm[:3, :3].T)
            out.append(np.r_[E_rot, T[:3, 3] - Tm[:3, 3]] * w)
        return np.concatenate(out)

    if not T_true:
        return inv_T(X), Y
    p = least_squares(corrections, np.zeros(12)).x
    A = T_from_Rt(R_from_rvec(p[:3]), p[3:6])
    B = T_from_Rt(R_from_rvec(p[6:9]), p[9:12])
    return inv_T(B @ X), Y @ A

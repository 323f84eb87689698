"""Forward and analytic inverse kinematics of the Universal Robots e-Series (pure numpy).

Standard DH parameters as Universal Robots publishes them (joint i: ``Rz(q_i) Tz(d_i) Tx(a_i)
Rx(alpha_i)``; base frame the controller's ``base``, frame 6 the flange), so ``fk(q)`` is
``T_base_tool`` of a zero TCP. Inverse kinematics: Hawkins' closed form (2013), eight
solutions for a generic pose. Joint limits +-360 deg, the elbow +-180 deg as in Universal
Robots' ROS description.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slidecal.solver.errors import InputError
from slidecal.solver.geometry import Rx, Rz, T_from_Rt, inv_T

#: ``|sin(q5)|`` below this is a wrist singularity (wrist joint speeds grow as ``1 / |sin(q5)|``).
WRIST_SIN_MIN = 0.05
#: ``|sin(q3)|`` below this is an elbow singularity (the arm stretched out or folded).
ELBOW_SIN_MIN = 0.05
#: Wrist point's distance (metres) from the base z axis below which the pose is shoulder-singular
#: (the base joint turns at ``v / r`` for a tool moving sideways at ``v``).
SHOULDER_RADIUS_MIN_M = 0.05


@dataclass(frozen=True)
class URModel:
    """DH lengths (metres) and joint limits (radians, (6,) each) of one UR arm."""

    name: str
    d1: float
    a2: float
    a3: float
    d4: float
    d5: float
    d6: float
    q_min: tuple[float, ...] = (-2 * np.pi, -2 * np.pi, -np.pi, -2 * np.pi, -2 * np.pi, -2 * np.pi)
    q_max: tuple[float, ...] = (2 * np.pi, 2 * np.pi, np.pi, 2 * np.pi, 2 * np.pi, 2 * np.pi)


# Universal Robots' published DH table (e-Series).
UR3E = URModel("UR3e", 0.15185, -0.24355, -0.2132, 0.13105, 0.08535, 0.0921)
UR5E = URModel("UR5e", 0.1625, -0.425, -0.3922, 0.1333, 0.0997, 0.0996)
UR10E = URModel("UR10e", 0.1807, -0.6127, -0.57155, 0.17415, 0.11985, 0.11655)
UR16E = URModel("UR16e", 0.1807, -0.4784, -0.36, 0.17415, 0.11985, 0.11655)
# CB3 arms (PolyScope 3.x), from the same published table: other lengths than the e-Series.
UR3 = URModel("UR3", 0.1519, -0.24365, -0.21325, 0.11235, 0.08535, 0.0819)
UR5 = URModel("UR5", 0.089159, -0.425, -0.39225, 0.10915, 0.09465, 0.0823)
UR10 = URModel("UR10", 0.1273, -0.612, -0.5723, 0.163941, 0.1157, 0.0922)
MODELS: dict[str, URModel] = {m.name.lower(): m for m in (UR3E, UR5E, UR10E, UR16E, UR3, UR5, UR10)}

#: A common "home" configuration (elbow up, tool pointing down), radians.
Q_HOME = np.array([0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0])


def model_by_name(name: str) -> URModel:
    """The :class:`URModel` of ``"UR5e"`` etc. (case-insensitive)."""
    try:
        return MODELS[name.lower()]
    except KeyError:
        raise InputError(
            f"unknown robot model {name!r}; use one of {', '.join(m.name for m in MODELS.values())}"
        ) from None


def trapezoid_time_s(distance: float, max_speed: float, max_accel: float) -> float:
    """Duration of a rest-to-rest trapezoidal move over ``distance`` (consistent units, linear or
    angular): ``2 sqrt(d / a)`` when too short to reach ``max_speed``, else ``d / v + v / a``."""
    d = abs(float(distance))
    if d <= max_speed**2 / max_accel:
        return 2.0 * float(np.sqrt(d / max_accel))
    return d / max_speed + max_speed / max_accel


def _dh(theta: float, d: float, a: float, alpha_rot: np.ndarray) -> np.ndarray:
    """``Rz(theta) Tz(d) Tx(a) Rx(alpha)`` as 4x4 (alpha given as its rotation matrix)."""
    Rzt = Rz(theta)
    return T_from_Rt(Rzt @ alpha_rot, Rzt @ np.array([a, 0.0, 0.0]) + np.array([0.0, 0.0, d]))


#: The nominal twists ``alpha_i`` (radians) and their rotations ``Rx(alpha_i)``.
ALPHAS = np.array([np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0])
ALPHA_ROTS = tuple(Rx(a) for a in ALPHAS)


def _check_q(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float).reshape(-1)
    if q.shape != (6,) or not np.all(np.isfinite(q)):
        raise InputError(f"a joint vector is 6 finite angles in radians, got {q!r}")
    return q


def _check_T(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f"a pose is a finite 4x4 transform, got shape {T.shape}")
    return T


def fk(
    q: np.ndarray,
    model: URModel = UR5E,
    T_flange_tcp: np.ndarray | None = None,
    dh_error: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """``T_base_tool`` (4, 4), metres, of joint angles ``q`` (6,) radians; ``T_flange_tcp`` (4, 4):
    the TCP offset (None: the flange); ``dh_error``: ``(d_d, d_a, d_alpha)`` (6,) each, metres and
    radians, added to the model's DH lengths and twists (a real arm, ``mocks/robot.py``)."""
    d_d, d_a, d_alpha = (0.0, 0.0, None) if dh_error is None else dh_error
    d = np.array([model.d1, 0.0, 0.0, model.d4, model.d5, model.d6]) + d_d
    a = np.array([0.0, model.a2, model.a3, 0.0, 0.0, 0.0]) + d_a
    rots = ALPHA_ROTS if d_alpha is None else tuple(Rx(v) for v in ALPHAS + d_alpha)
    T = np.eye(4)
    for i, theta in enumerate(_check_q(q)):
        T = T @ _dh(theta, d[i], a[i], rots[i])
    return T if T_flange_tcp is None else T @ T_flange_tcp


#: ``|sin(q5)|`` below which the wrist is treated as exactly singular (q6 free) in the IK.
_WRIST_EXACT = 1e-7
_EPS = float(np.finfo(float).eps)


def _acos(x: float, tol: float = 1e-10) -> float | None:
    """arccos, tolerating rounding up to ``tol`` outside [-1, 1]; None when truly outside."""
    if abs(x) > 1.0 + tol:
        return None
    return float(np.arccos(np.clip(x, -1.0, 1.0)))


def _ik_flange(T: np.ndarray, m: URModel, q6_singular: float = 0.0) -> list[np.ndarray]:
    """All closed-form solutions (angles in (-pi, pi]) for the flange pose ``T`` (Hawkins 2013); at
    a wrist singularity q6 is ``q6_singular``."""
    R = T[:3, :3]
    p06 = T[:3, 3]
    p05 = p06 - m.d6 * R[:, 2]
    rho = float(np.hypot(p05[0], p05[1]))
    if rho < 1e-12:
        return []
    phi = _acos(m.d4 / rho)
    if phi is None:
        return []
    sols: list[np.ndarray] = []
    for s1 in (1.0, -1.0):
        q1 = np.arctan2(p05[1], p05[0]) + s1 * phi + np.pi / 2
        c1, sn1 = np.cos(q1), np.sin(q1)
        c5 = (p06[0] * sn1 - p06[1] * c1 - m.d4) / m.d6
        a5 = _acos(c5)
        if a5 is None:
            continue
        for s5 in (1.0, -1.0):
            q5 = s5 * a5
            sn5 = np.sin(q5)
            if abs(sn5) < _WRIST_EXACT:
                q6 = q6_singular  # wrist singular: q4 and q6 are coupled, q6 is free
            else:
                q6 = np.arctan2(
                    (-R[0, 1] * sn1 + R[1, 1] * c1) / sn5, (R[0, 0] * sn1 - R[1, 0] * c1) / sn5
                )
            T01 = _dh(q1, m.d1, 0.0, ALPHA_ROTS[0])
            T45 = _dh(q5, m.d5, 0.0, ALPHA_ROTS[4])
            T56 = _dh(q6, m.d6, 0.0, ALPHA_ROTS[5])
            T14 = inv_T(T01) @ T @ inv_T(T45 @ T56)
            px, py = T14[0, 3], T14[1, 3]
            # Near a wrist singularity q5 comes from arccos(c5) with an error of about
            # eps / |sin(q5)| (1e-9 rad at 1e-7 rad from singular), which moves the wrist point
            # by (d5 + d6) times that; a stretched elbow then sees its cosine pushed past 1 by
            # r (d5 + d6) eps / (|a2 a3| |sin(q5)|): tolerate 8 times that (nanometres of reach).
            r = float(np.hypot(px, py))
            tol = 1e-10 + 8.0 * r * (m.d5 + m.d6) * _EPS / (
                abs(m.a2 * m.a3) * max(abs(float(sn5)), _WRIST_EXACT)
            )
            a3 = _acos((px * px + py * py - m.a2**2 - m.a3**2) / (2.0 * m.a2 * m.a3), tol)
            if a3 is None:
                continue
            q234 = np.arctan2(T14[1, 0], T14[0, 0])
            for s3 in (1.0, -1.0):
                q3 = s3 * a3
                q2 = np.arctan2(py, px) - np.arctan2(m.a3 * np.sin(q3), m.a2 + m.a3 * np.cos(q3))
                q4 = q234 - q2 - q3
                sols.append((np.array([q1, q2, q3, q4, q5, q6]) + np.pi) % (2 * np.pi) - np.pi)
    return sols


def _nearest_within_limits(q: np.ndarray, q_near: np.ndarray, m: URModel) -> np.ndarray | None:
    """Each angle shifted by a multiple of 2 pi to be nearest ``q_near`` inside the limits."""
    out = np.empty(6)
    for i in range(6):
        k = np.round((q_near[i] - q[i]) / (2 * np.pi))
        cands = [q[i] + 2 * np.pi * (k + j) for j in (-1, 0, 1)]
        ok = [c for c in cands if m.q_min[i] - 1e-9 <= c <= m.q_max[i] + 1e-9]
        if not ok:
            return None
        out[i] = min(ok, key=lambda c, i=i: abs(c - q_near[i]))
    return out


def ik(
    T_base_tool: np.ndarray,
    q_near: np.ndarray | None = None,
    model: URModel = UR5E,
    T_flange_tcp: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Joint solutions (each (6,), radians) reaching ``T_base_tool`` (4, 4, metres) inside the joint
    limits, each angle shifted by whole turns toward ``q_near`` (6,) and sorted by distance to it
    when given; empty when out of reach."""
    T = _check_T(T_base_tool)
    if T_flange_tcp is not None:
        T = T @ inv_T(_check_T(T_flange_tcp))
    sols: list[np.ndarray] = []
    qn = None if q_near is None else _check_q(q_near)
    for q in _ik_flange(T, model, 0.0 if qn is None else float(qn[5])):
        qq = _nearest_within_limits(q, q if qn is None else qn, model)
        # duplicates (at most 8 solutions): a max-abs test, cheaper than np.allclose
        if qq is not None and not any(float(np.max(np.abs(qq - s))) <= 1e-9 for s in sols):
            sols.append(qq)
    if qn is not None:
        sols.sort(key=lambda s: float(np.max(np.abs(s - qn))))
    return sols


def singularity(q: np.ndarray, model: URModel = UR5E) -> str | None:
    """Which singularity the configuration ``q`` (6,) radians is near (:data:`WRIST_SIN_MIN`,
    :data:`ELBOW_SIN_MIN`, :data:`SHOULDER_RADIUS_MIN_M`), or None."""
    q = _check_q(q)
    if abs(np.sin(q[4])) < WRIST_SIN_MIN:
        return f"wrist singularity (q5 = {np.degrees(q[4]):.1f} deg, axes 4 and 6 aligned)"
    if abs(np.sin(q[2])) < ELBOW_SIN_MIN:
        return f"elbow singularity (q3 = {np.degrees(q[2]):.1f} deg, arm stretched or folded)"
    # Horizontal distance of the wrist point from the base axis, in the arm's plane.
    r = model.a2 * np.cos(q[1]) + model.a3 * np.cos(q[1] + q[2]) + model.d5 * np.sin(
        q[1] + q[2] + q[3]
    )
    if abs(r) < SHOULDER_RADIUS_MIN_M:
        return f"shoulder singularity (wrist point {abs(r) * 1000:.0f} mm from the base axis)"
    return None


def reachable(
    T_base_tool: np.ndarray,
    q_near: np.ndarray | None = None,
    model: URModel = UR5E,
    T_flange_tcp: np.ndarray | None = None,
) -> bool:
    """Whether ``T_base_tool`` (4, 4, metres) has a non-singular solution inside the limits (with
    ``q_near`` (6,) rad: the solution nearest it, as a linear move from there would use)."""
    sols = ik(T_base_tool, q_near, model, T_flange_tcp)
    if q_near is not None:
        sols = sols[:1]
    return any(singularity(q, model) is None for q in sols)

"""slidecal.solver: the pure maths (a frozen problem in, a result out; no I/O, no logging).

The contract is listed in ``__all__``: the pipeline, the problem and result types, the named
covariance (:mod:`slidecal.solver.uncertainty` names the reported quantities: ``cam.fx``,
``T_tool_cam.rx`` .. ``.tz``), the predicted covariance of a plan, the mount names and the
errors. Each name is imported on first use, so importing the package stays light. The
optimiser's own coordinates and the error model's terms are internal to their modules.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    # the pipeline
    "calibrate": "calibrate",
    "check_problem": "calibrate",
    # inputs
    "CalibrationProblem": "problem",
    "CameraSpec": "problem",
    "Detection": "problem",
    "Frame": "problem",
    "ModelOptions": "problem",
    "Target": "problem",
    "MOUNTS": "problem",
    "MountNames": "problem",
    "mount_names": "problem",
    "hand_eye_names": "problem",
    # results
    "CalibrationResult": "result",
    "CameraEstimate": "result",
    "TransformEstimate": "result",
    "NamedCovariance": "result",
    # the uncertainty of a plan
    "predicted_covariance": "uncertainty",
    # errors
    "SlidecalError": "errors",
    "InputError": "errors",
    "DegenerateError": "errors",
    "HardwareFault": "errors",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    """Import a public name from its module on first use."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'slidecal.solver' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"slidecal.solver.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

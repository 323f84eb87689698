"""slidecal.solver: the pure maths (a frozen problem in, a result out; no I/O, no logging).

The public API is listed in ``__all__``; each name is imported on first use, so importing the
package stays light. The reported quantities and their covariance are named by
:mod:`slidecal.solver.named` (``cam.fx``, ``T_tool_cam.rx`` .. ``.tz``); the optimiser's own
coordinates (:mod:`slidecal.solver.refine`) are private to it.
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
    # results
    "CalibrationResult": "result",
    "CameraEstimate": "result",
    "TransformEstimate": "result",
    # the named model
    "MOUNTS": "named",
    "MountNames": "named",
    "NamedCovariance": "named",
    "FrameInformation": "named",
    "mount_names": "named",
    "hand_eye_names": "named",
    "predicted_covariance": "named",
    "equal_weight_covariance": "named",
    "frame_information": "named",
    "LinearisedEstimator": "named",
    "linearised_estimator": "named",
    # errors
    "SlidecalError": "errors",
    "InputError": "errors",
    "DegenerateError": "errors",
    "ConvergenceError": "errors",
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

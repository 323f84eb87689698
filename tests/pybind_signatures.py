"""The fakes of pybind11 libraries (depthai, ur-rtde) checked against the installed ones.

pybind11 callables carry no ``inspect.signature``; their docstrings start with one line per
overload, ``name(self: T, a: int, b: float = 1.0) -> R``. :func:`check_callable` asserts that
a fake method's parameters match one overload by position and name (pybind's ``argN`` names are
positional only), so a renamed keyword or a missing parameter in a fake fails a test.
"""

from __future__ import annotations

import inspect
import re


def overloads(real, name):
    """Parameter lists ``[(name, has_default), ...]`` of a pybind11 callable's overloads."""
    doc = inspect.getdoc(real) or ""
    out = []
    for m in re.finditer(rf"^(?:\d+\. )?{re.escape(name)}\((.*)\) ->", doc, re.M):
        params, depth, cur = [], 0, ""
        for ch in m.group(1) + ",":
            if ch in "[(<{":
                depth += 1
            elif ch in "])>}":
                depth -= 1
            if ch == "," and depth == 0:
                params.append(cur.strip())
                cur = ""
            else:
                cur += ch
        out.append([(p.split(":")[0].strip(), "=" in p) for p in params if p and p != "self"
                    and not p.startswith("self:")])
    return out


def check_callable(fake, real, name, where):
    assert callable(real), f"{where}: the fake has a method, the library has {type(real).__name__}"
    found = overloads(real, name)
    if not found:
        return  # not introspectable (no signature in the docstring)
    sig = inspect.signature(fake)
    mine = [p for p in sig.parameters.values() if p.name != "self"]
    names = [p.name for p in mine]
    for params in found:
        real = [(p, d) for p, d in params if not p.startswith("*")]
        if len(names) > len(real) or any(not d for _, d in real[len(names):]):
            continue  # the fake takes more, or lacks a parameter the library requires
        # by position and by name (pybind's argN names are positional only)
        pairs = zip(real[: len(names)], names, strict=True)
        if all(r == n or re.fullmatch(r"arg\d+", r) for (r, _), n in pairs):
            return
    raise AssertionError(f"{where}{sig} matches no overload of the library's: {found}")

"""The format layer's common part: strict YAML reading (:func:`load_yaml`: UTF-8, no key twice
in a mapping) and typed, named access to fields (:class:`Fields`: declared keys, an unknown one
refused with the nearest valid one; finite numbers, shaped arrays, positive sizes, choices).
Every failure is one :class:`~slidecal.solver.errors.InputError` line naming ``file: field``,
what is wrong and how to fix it."""

from __future__ import annotations

import difflib
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from slidecal.solver.camera import DISTORTION_MODELS
from slidecal.solver.errors import InputError

_BaseLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_Dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


MERGE = "tag:yaml.org,2002:merge"  # '<<: *anchor' merges a mapping, it is not a key


class DuplicateKeyError(Exception):
    """A key given twice in one YAML mapping (PyYAML would keep the last silently); ``args``:
    the two key nodes."""


class StrictLoader(_BaseLoader):  # type: ignore[misc, valid-type]
    """The safe YAML loader, refusing a key that appears twice in one mapping (keys compared only
    where a mapping's dict is shorter than its list of keys)."""

    def construct_mapping(self, node: Any, deep: bool = False) -> dict[Any, Any]:
        pairs = node.value[:]  # flatten_mapping rewrites node.value when it merges
        data = super().construct_mapping(node, deep=deep)
        if len(data) != len(pairs):
            seen: dict[Any, Any] = {}
            for key_node, _ in pairs:
                if key_node.tag == MERGE:
                    continue
                key = self.construct_object(key_node, deep=True)
                if key in seen:
                    raise DuplicateKeyError(seen[key], key_node)
                seen[key] = key_node
        return data


# ----------------------------------------------------------------------------- reading, writing


def plain(obj: Any) -> Any:
    """``obj`` with numpy arrays and scalars turned into lists and Python numbers (for YAML)."""
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Mapping):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [plain(v) for v in obj]
    return obj


def dump_yaml(data: Any, indent: int | None = None) -> str:
    """YAML text of ``data`` (numbers in flow-style leaf lists, keys in insertion order).
    ``indent``: ``data`` is a part of a document nested that many spaces deep, dumped so that
    parts join into the whole document's text."""
    text = yaml.dump(
        plain(data),
        Dumper=_Dumper,
        default_flow_style=None,
        sort_keys=False,
        width=100 - (indent or 0),
    )
    return "".join(" " * indent + line for line in text.splitlines(True)) if indent else text


def write_atomic(path: Path, text: str | bytes) -> None:
    """Write ``path`` so that it holds either its old or its new content: a fsynced temporary file
    renamed over it, the directory fsynced; on failure the temporary file is removed."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    data = text.encode() if isinstance(text, str) else text
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:  # a full disk, a signal: leave the old file and no temporary one
        try:
            tmp.unlink()
        except OSError:
            pass
        raise
    _fsync_dir(path.parent)


def write_yaml(path: str | Path, data: Any) -> Path:
    """Write ``data`` as YAML at ``path`` (:func:`write_atomic`, its folder created); return it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, dump_yaml(data))
    return path


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # platforms without directory handles (Windows)
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def read_text(path: Path, what: str) -> str:
    """The UTF-8 text of a file; a missing, unreadable or non-UTF-8 file is an ``InputError``."""
    path = Path(path)
    if not path.is_file():
        if path.is_dir():
            raise InputError(f"is a directory, not a {what}; give the file", where=str(path))
        raise InputError(f"{what} not found; check the path", where=str(path))
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise InputError(
            f"cannot be read ({e.strerror or e}); check its permissions", where=str(path)
        ) from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(
            f"is not UTF-8 text (byte 0x{raw[e.start]:02x} at offset {e.start}); save the "
            f"{what} as UTF-8",
            where=path.name,
        ) from None


def parse_yaml(text: str, source: str) -> Any:
    """Parse YAML text strictly (a key twice in one mapping is refused, naming its field);
    errors name ``source`` and the line."""
    try:
        loader = StrictLoader(text)
        try:
            node = loader.get_single_node()
            if node is None:
                return None
            try:
                return loader.construct_document(node)
            except DuplicateKeyError as e:
                first, second = (k.start_mark.line + 1 for k in e.args)
                raise InputError(
                    f"appears twice (lines {first} and {second}); keep one",
                    where=f"{source}: {_field(node, e.args[1], '', set())}",
                ) from None
        finally:
            loader.dispose()
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        line = f" at line {mark.line + 1}" if mark is not None else ""
        problem = " ".join(str(getattr(e, "problem", None) or e).split())
        raise InputError(
            f"not valid YAML{line} ({problem}); fix the syntax", where=source
        ) from None
    except RecursionError:
        raise InputError("nests too deeply to be a slidecal file", where=source) from None


def _field(node: Any, key: Any, path: str, seen: set[int]) -> str | None:
    """The field path of the key node ``key`` in the composed YAML ``node`` (None: not there)."""
    if id(node) in seen:  # an alias of a node already walked
        return None
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        items = [(f"{path}.{k.value}" if path else str(k.value), k, v) for k, v in node.value]
    elif isinstance(node, yaml.SequenceNode):
        items = [(f"{path}[{i}]", None, v) for i, v in enumerate(node.value)]
    else:
        return None
    for field, key_node, value in items:
        found = field if key_node is key else _field(value, key, field, seen)
        if found is not None:
            return found
    return None


def load_yaml(path: Path, what: str) -> Any:
    """Read and parse a YAML file (UTF-8, strict); every problem is an ``InputError``."""
    path = Path(path)
    data = parse_yaml(read_text(path, what), path.name)
    if data is None:
        raise InputError(f"is empty; it must hold a {what}", where=path.name)
    return data


# ----------------------------------------------------------------------------- field checks


#: the cell file's top-level sections (routines/config.py validates each; a solve reads limits:)
CELL_SECTIONS = (
    "format",
    "mount",
    "robot",
    "cameras",
    "target",
    "approximate",
    "simulation",
    "plan",
    "options",
    "limits",  # the verdict's limits (routines/ops/verdict.py: limits_from_dict)
    "install",  # the install store (INSTALL_KEYS)
)


def nearest(key: str, valid: Iterable[str]) -> str | None:
    """The valid key closest to a misspelt ``key`` (None when nothing is close)."""
    valid = list(valid)
    match = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
    if match:
        return match[0]
    low = {v.lower(): v for v in valid}
    return low.get(key.lower())


def unknown_key_error(where: str, key: Any, valid: Sequence[str]) -> InputError:
    """``where: unknown key; did you mean X?`` (or the list of valid keys)."""
    hint = nearest(str(key), valid) if isinstance(key, str) else None
    if hint is not None:
        return InputError(f"unknown key; did you mean {hint}?", where=where)
    return InputError(f"unknown key; the keys here are {', '.join(valid)}", where=where)


class Fields:
    """Typed access to one mapping of a YAML file; every failure names ``file: path.field``."""

    def __init__(self, data: Any, file: str, path: str = "") -> None:
        self.file, self.path = file, path
        if not isinstance(data, Mapping):
            raise InputError(f"must be a mapping of fields, got {_kind(data)}", where=self.where())
        self.data = data

    def where(self, key: str | None = None) -> str:
        """``file: path.key`` for error messages (a key that is not printable text quoted)."""
        if key is not None and not (key.isprintable() and key.strip() == key and key):
            key = repr(key)
        p = self.path if key is None else (f"{self.path}.{key}" if self.path else key)
        return f"{self.file}: {p}" if p else self.file

    def error(self, key: str | None, message: str) -> InputError:
        """An ``InputError`` about ``key``."""
        return InputError(message, where=self.where(key))

    def only(self, valid: Sequence[str]) -> Fields:
        """Refuse any key not in ``valid`` (the section's declared keys), naming the nearest."""
        for key in self.data:
            if key not in valid:
                raise unknown_key_error(self.where(str(key)), key, valid)
        return self

    def has(self, key: str) -> bool:
        """Whether ``key`` is present and not null."""
        return self.data.get(key) is not None

    def get(self, key: str, default: Any = None) -> Any:
        """The raw value, ``default`` when absent or null."""
        v = self.data.get(key)
        return default if v is None else v

    def require(self, key: str) -> Any:
        """The raw value; a missing key is an error."""
        if not self.has(key):
            raise self.error(key, "is missing; add it (docs/FORMATS.md lists every field)")
        return self.data[key]

    def sub(self, key: str, required: bool = True) -> Fields | None:
        """The nested mapping at ``key``."""
        if not required and not self.has(key):
            return None
        return Fields(self.require(key), self.file, f"{self.path}.{key}" if self.path else key)

    def section(self, key: str, valid: Sequence[str] | None = None) -> Fields:
        """The nested mapping at ``key`` (empty when absent), restricted to ``valid`` keys."""
        sub = self.sub(key, required=False)
        sub = sub if sub is not None else Fields({}, self.file, self.where(key).split(": ")[-1])
        return sub.only(valid) if valid is not None else sub

    def cameras(self, names: Sequence[str] | None = None) -> Iterator[str]:
        """The keys of a per-camera mapping, each refused unless one of ``names`` (None: unless
        a name as text)."""
        for key in self.data:
            if names is None and (not isinstance(key, str) or not key.strip()):
                raise self.error(str(key), "must be a camera name (text)")
            if names is not None and key not in names:
                raise self.error(str(key), f"unknown camera {key!r}; cameras are {list(names)}")
            yield str(key)

    def camera(self, key: str, names: Sequence[str]) -> str:
        """A camera's name among ``names`` (the first when absent)."""
        name = self.string(key, names[0])
        if name not in names:
            raise self.error(key, f"{name!r} is not a camera; cameras are {list(names)}")
        return name

    def choice(self, key: str, options: Sequence[str], default: str | None = None) -> str:
        """A string among ``options``."""
        v = self.get(key, default) if default is not None else self.require(key)
        if not isinstance(v, str) or v not in options:
            hint = nearest(v, options) if isinstance(v, str) else None
            more = f" (did you mean {hint}?)" if hint else ""
            raise self.error(key, f"is {v!r}{more}; use one of {', '.join(options)}")
        return str(v)

    def number(
        self,
        key: str,
        default: float | None = None,
        positive: bool = False,
        minimum: float | None = None,
        maximum: float | None = None,
    ) -> float:
        """A finite float (optionally > 0, >= minimum, <= maximum)."""
        v = self.require(key) if default is None else self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise self.error(key, f"must be a number, got {v!r}")
        if not np.isfinite(v):
            raise self.error(key, f"must be a finite number, got {v!r}")
        if positive and v <= 0:
            raise self.error(key, f"must be positive, got {v!r}")
        if minimum is not None and v < minimum:
            raise self.error(key, f"must be at least {minimum:g}, got {v!r}")
        if maximum is not None and v > maximum:
            raise self.error(key, f"must be at most {maximum:g}, got {v!r}")
        return float(v)

    def optional_number(self, key: str, **kw: Any) -> float | None:
        """A number as :meth:`number`, or None when absent or null."""
        return self.number(key, **kw) if self.has(key) else None

    def integer(
        self,
        key: str,
        default: int | None = None,
        minimum: int | None = None,
        maximum: int | None = None,
    ) -> int:
        """An int (optionally >= minimum, <= maximum)."""
        v = self.require(key) if default is None else self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.error(key, f"must be an integer, got {v!r}")
        if minimum is not None and v < minimum:
            raise self.error(key, f"must be at least {minimum}, got {v!r}")
        if maximum is not None and v > maximum:
            raise self.error(key, f"must be at most {maximum}, got {v!r}")
        return int(v)

    def boolean(self, key: str, default: bool | None = None) -> bool:
        """A bool."""
        v = self.require(key) if default is None else self.get(key, default)
        if not isinstance(v, bool):
            raise self.error(key, f"must be true or false, got {v!r}")
        return v

    def string(self, key: str, default: str | None = None) -> str:
        """A non-empty string."""
        v = self.require(key) if default is None else self.get(key, default)
        if not isinstance(v, str) or not v.strip():
            raise self.error(key, f"must be a non-empty string, got {v!r}")
        return v

    def array(self, key: str, shape: tuple[int, ...], default: Any = None) -> np.ndarray:
        """A float array of ``shape`` (-1 for any length), finite."""
        v = self.require(key) if default is None else self.get(key, default)
        return as_array(v, shape, self.where(key))

    def distortion(self, key: str) -> np.ndarray:
        """A lens's distortion vector: its length names the model (``solver/camera.py``)."""
        d = self.array(key, (-1,))
        if len(d) not in {len(v) for v in DISTORTION_MODELS.values()}:
            models = "; ".join(
                f"{len(v)} for {m} ({' '.join(v)})" for m, v in DISTORTION_MODELS.items()
            )
            raise self.error(key, f"has {len(d)} values; give {models}")
        return d

    def rotation(self, key: str, advice: str = "") -> np.ndarray:
        """A 3x3 rotation matrix (orthonormal, det +1); ``advice`` ends the message refusing one."""
        R = self.array(key, (3, 3))
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
            raise self.error(key, f"is not a rotation matrix (orthonormal, det +1){advice}")
        return R

    def list(
        self, key: str, required: bool = True, non_empty: bool = False, hint: str = "an entry"
    ) -> list[Any]:
        """A YAML list (empty when absent and not required); ``hint``: what an entry is."""
        if not required and not self.has(key):
            return []
        v = self.require(key)
        if not isinstance(v, list):
            raise self.error(key, f"must be a list of {hint}, got {_kind(v)}")
        if non_empty and not v:
            raise self.error(key, f"is empty; give a list of at least one {hint}")
        return v

    def entries(self, key: str, valid: Sequence[str] | None = None, **kw: Any) -> Iterator[Fields]:
        """The mappings of the list ``key`` (:meth:`list`, ``kw`` its options), each one's fields
        named ``key[i]`` and restricted to the ``valid`` keys."""
        path = f"{self.path}.{key}" if self.path else key
        for i, item in enumerate(self.list(key, **kw)):
            entry = Fields(item, self.file, f"{path}[{i}]")
            yield entry if valid is None else entry.only(valid)

    def strings(self, key: str) -> list[str]:
        """A list of strings (empty when absent)."""
        v = self.list(key, required=False)
        for i, s in enumerate(v):
            if not isinstance(s, str):
                raise self.error(f"{key}[{i}]", f"must be a string, got {s!r}")
        return v


def _kind(value: Any) -> str:
    return {
        "NoneType": "nothing (null)",
        "str": f"the text {value!r}" if isinstance(value, str) and len(value) < 40 else "text",
        "list": "a list",
        "dict": "a mapping",
        "int": f"the number {value!r}",
        "float": f"the number {value!r}",
        "bool": f"{value!r}",
    }.get(type(value).__name__, type(value).__name__)


def as_array(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (-1: any length); else an ``InputError``."""
    want = "x".join("n" if s < 0 else str(s) for s in shape)
    if not _only_numbers(value):
        raise InputError(f"must be a {want} array of numbers, got {_short(value)}", where=where)
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(
            f"must be a {want} array of numbers (rows of equal length), got {_short(value)}",
            where=where,
        ) from None
    if a.size == 0 and len(shape) == 2 and shape[0] < 0:
        a = a.reshape(0, shape[1] if shape[1] >= 0 else 0)
    ok = a.ndim == len(shape) and all(s < 0 or s == n for s, n in zip(shape, a.shape, strict=True))
    if not ok:
        raise InputError(f"must be a {want} array, got shape {list(a.shape)}", where=where)
    if not np.all(np.isfinite(a)):
        raise InputError("must hold finite numbers only (no NaN, no inf)", where=where)
    return a


def _only_numbers(value: Any, depth: int = 0) -> bool:
    if depth > 4:
        return False
    if isinstance(value, bool):
        return False
    if isinstance(value, int | float | np.integer | np.floating):
        return True
    if isinstance(value, list | tuple | np.ndarray):
        return all(_only_numbers(v, depth + 1) for v in value)
    return False


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def check_out_dir(out: Path, what: str = "--out") -> None:
    """Refuse an output directory that cannot be one: empty, a file, under a file, or not
    writable (checked on the nearest existing parent; nothing is created here)."""
    if str(out) in ("", "."):
        raise InputError(f"{what} is empty or '.'; name a new directory for the session")
    if out.exists() and not out.is_dir():
        raise InputError(f"is a file; {what} must name a directory", where=str(out))
    p = out
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    if p.exists() and not p.is_dir():
        raise InputError(f"{p} is a file; {what} must lie under a directory", where=str(out))
    if p.exists() and not os.access(p, os.W_OK | os.X_OK):
        raise InputError(
            f"cannot be written ({p} is read-only for this user); choose a writable {what}",
            where=str(out),
        )


def check_out_file(path: Path, what: str = "--out") -> None:
    """Refuse an output file that is a directory or lies under a file or a read-only place."""
    if str(path) in ("", "."):
        raise InputError(f"{what} is empty; name a file")
    if path.is_dir():
        raise InputError(f"is a directory; {what} must name a file", where=str(path))
    if str(path.parent) not in ("", "."):
        check_out_dir(path.parent, what)

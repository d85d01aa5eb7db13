"""A checkpoint codec that carries data and no code: numpy arrays plus a JSON tree.

`encode(obj)` walks the object graph and accepts only: None, bool, int, float, str, bytes,
list, tuple, dict, deque, set, numpy arrays and scalars (numeric and bool dtypes), enums, and
instances of classes from the allowed modules (dataclasses, NamedTuples, plain classes with
`__dict__` or `__slots__`), whose state is walked the same way. Anything else (a function, a
lambda, a class from elsewhere, an object array) raises `StateCodecError`. So a new field made of
those types needs no format change.

`decode(data, allowed_modules)` rebuilds the graph: classes are looked up by name only inside
the allowed modules and made with `cls.__new__` (no `__init__`, no `__reduce__` callables), then
given their state as pickle would (`__setstate__` if the class has one, else attribute by
attribute), so existing compatibility hooks (`ManhattanEstimator.__setstate__`) keep working.
Shared references and cycles are kept, as pickle keeps them.

The bytes are an `.npz` (zip, deflate-compressed): `tree.json` plus one `.npy` per array, read
with `allow_pickle=False`.
"""

from __future__ import annotations

import base64
import collections
import copyreg
import enum
import importlib
import io
import json
import math
import zipfile
from collections.abc import Iterable
from typing import Any, Final

import numpy as np

FORMAT: Final = 1
_NEWOBJ: Final = getattr(copyreg, "__newobj__")  # noqa: B009  # untyped in typeshed
_TREE = "tree.json"
_ALLOWED_DTYPE_KINDS: Final = "biufcmM"  # numbers, booleans, timestamps: never objects
# Deflate's fastest level: a checkpoint is encoded on the session's path (a mapper process
# blocks its sessions meanwhile), and its arrays are mostly the map chunks' unknown cells. A
# 415 m loop's state with loop closure (84 MB of arrays): level 6 908 ms, 10.3 MB; level 1
# 561 ms, 11.1 MB. Decoding does not depend on the level.
COMPRESS_LEVEL: Final = 1


class StateCodecError(ValueError):
    """An object the codec refuses to write, or bytes it refuses to read."""


def _allowed(module: str, allowed: Iterable[str]) -> bool:
    return any(module == a or module.startswith(a + ".") for a in allowed)


class _Encoder:
    def __init__(self, allowed: tuple[str, ...]) -> None:
        self.allowed = allowed
        self.arrays: list[np.ndarray[Any, Any]] = []
        self.memo: dict[int, int] = {}  # id(obj) -> reference number
        self.keep: list[object] = []  # keep ids stable while encoding
        self.next_ref = 0

    def _remember(self, obj: object) -> int | None:
        """A reference number for a container/object seen before, else register it."""
        key = id(obj)
        if key in self.memo:
            return self.memo[key]
        self.memo[key] = self.next_ref
        self.next_ref += 1
        self.keep.append(obj)
        return None

    def walk(self, obj: Any) -> Any:
        if isinstance(obj, enum.Enum):
            cls = type(obj)
            self._check_class(cls)
            return {"e": _name(cls), "v": self.walk(obj.value)}
        if obj is None or type(obj) is str or type(obj) is bool:
            return obj
        if type(obj) is int:
            return obj
        if type(obj) is float:
            return obj if math.isfinite(obj) else {"f": repr(obj)}
        if isinstance(obj, np.generic):
            if obj.dtype.kind not in _ALLOWED_DTYPE_KINDS:
                raise StateCodecError(f"numpy scalar of dtype {obj.dtype} refused")
            self.arrays.append(np.asarray(obj))
            return {"s": len(self.arrays) - 1}
        seen = self._remember(obj)
        if seen is not None:
            return {"r": seen}
        ref = self.next_ref - 1
        if isinstance(obj, np.ndarray):
            if obj.dtype.kind not in _ALLOWED_DTYPE_KINDS:
                raise StateCodecError(f"numpy array of dtype {obj.dtype} refused")
            self.arrays.append(obj)
            return {"a": len(self.arrays) - 1, "n": ref}
        if type(obj) is bytes:
            return {"b": base64.b64encode(obj).decode(), "n": ref}
        if type(obj) is list:
            return {"l": [self.walk(v) for v in obj], "n": ref}
        if type(obj) is tuple:
            return {"t": [self.walk(v) for v in obj], "n": ref}
        if type(obj) is dict:
            return {"d": [[self.walk(k), self.walk(v)] for k, v in obj.items()], "n": ref}
        if type(obj) is set or type(obj) is frozenset:
            items = sorted(obj, key=repr)
            return {
                "set": [self.walk(v) for v in items],
                "frozen": type(obj) is frozenset,
                "n": ref,
            }
        if type(obj) is collections.deque:
            return {"q": [self.walk(v) for v in obj], "maxlen": obj.maxlen, "n": ref}
        return self._object(obj, ref)

    def _check_class(self, cls: type) -> None:
        if not _allowed(cls.__module__, self.allowed) or "<locals>" in cls.__qualname__:
            raise StateCodecError(f"objects of class {_name(cls)} are not allowed in a checkpoint")

    def _object(self, obj: Any, ref: int) -> Any:
        cls = type(obj)
        self._check_class(cls)
        if isinstance(obj, type) or (callable(obj) and not hasattr(obj, "__dict__")):
            raise StateCodecError(f"{_name(cls)}: code is not allowed in a checkpoint")
        reduced = obj.__reduce_ex__(2)
        if not isinstance(reduced, tuple) or reduced[0] is not _NEWOBJ:
            raise StateCodecError(f"{_name(cls)} does not reduce to plain construction")
        args = reduced[1][1:]
        state = reduced[2] if len(reduced) > 2 else None
        if len(reduced) > 3 and (reduced[3] is not None or reduced[4] is not None):
            raise StateCodecError(f"{_name(cls)}: list/dict subclasses are not supported")
        return {
            "o": _name(cls),
            "args": [self.walk(a) for a in args],
            "state": self.walk(state),
            "n": ref,
        }


def _name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


class _Decoder:
    def __init__(self, arrays: dict[str, np.ndarray[Any, Any]], allowed: tuple[str, ...]) -> None:
        self.arrays = arrays
        self.allowed = allowed
        self.refs: dict[int, Any] = {}

    def cls(self, name: str) -> type:
        module, _, qualname = name.partition(":")
        if not _allowed(module, self.allowed) or not qualname:
            raise StateCodecError(f"class {name} is not allowed in a checkpoint")
        target: Any = importlib.import_module(module)
        for part in qualname.split("."):
            target = getattr(target, part, None)
        if not isinstance(target, type):
            raise StateCodecError(f"{name} is not a class")
        return target

    def array(self, index: Any) -> np.ndarray[Any, Any]:
        try:
            return self.arrays[f"a{int(index)}"]
        except KeyError as err:
            raise StateCodecError(f"array {index} missing") from err

    def walk(self, node: Any) -> Any:
        if node is None or isinstance(node, str | bool | int | float):
            return node
        if isinstance(node, list):
            raise StateCodecError("untagged list")
        if not isinstance(node, dict):
            raise StateCodecError(f"unexpected node {type(node).__name__}")
        if "f" in node:
            return float(node["f"])
        if "s" in node:
            return self.array(node["s"])[()]
        if "r" in node:
            try:
                return self.refs[int(node["r"])]
            except KeyError as err:
                raise StateCodecError("dangling reference") from err
        if "e" in node:
            return self.cls(node["e"])(self.walk(node["v"]))
        ref = int(node["n"])
        if "a" in node:
            value: Any = self.array(node["a"])
        elif "b" in node:
            value = base64.b64decode(node["b"])
        elif "t" in node:
            value = tuple(self.walk(v) for v in node["t"])
        elif "l" in node:
            value = []
            self.refs[ref] = value
            value.extend(self.walk(v) for v in node["l"])
        elif "d" in node:
            value = {}
            self.refs[ref] = value
            for k, v in node["d"]:
                value[self.walk(k)] = self.walk(v)
        elif "set" in node:
            items = [self.walk(v) for v in node["set"]]
            value = frozenset(items) if node.get("frozen") else set(items)
        elif "q" in node:
            maxlen = node.get("maxlen")
            value = collections.deque(maxlen=None if maxlen is None else int(maxlen))
            self.refs[ref] = value
            value.extend(self.walk(v) for v in node["q"])
        elif "o" in node:
            cls = self.cls(node["o"])
            args = [self.walk(a) for a in node.get("args", [])]
            value = cls.__new__(cls, *args)
            self.refs[ref] = value
            _set_state(value, self.walk(node.get("state")))
        else:
            raise StateCodecError(f"unknown node {sorted(node)[:3]}")
        self.refs[ref] = value
        return value


def _set_state(obj: Any, state: Any) -> None:
    """Apply a reduced state the way pickle does."""
    if state is None:
        return
    setstate = getattr(obj, "__setstate__", None)
    if setstate is not None:
        setstate(state)
        return
    slots: Any = None
    if isinstance(state, tuple) and len(state) == 2:
        state, slots = state
    if state:
        obj.__dict__.update(state)
    if slots:
        for key, value in slots.items():
            object.__setattr__(obj, key, value)


def encode(obj: object, allowed_modules: Iterable[str]) -> bytes:
    """`obj` as compressed bytes; `StateCodecError` if the graph holds anything not allowed."""
    encoder = _Encoder(tuple(allowed_modules))
    try:
        tree = {"format": FORMAT, "root": encoder.walk(obj)}
    except RecursionError as err:
        raise StateCodecError("object graph too deep") from err
    buf = io.BytesIO()
    arrays = {f"a{i}": a for i, a in enumerate(encoder.arrays)}
    deflate = zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(buf, "w", compression=deflate, compresslevel=COMPRESS_LEVEL) as zf:
        zf.writestr(_TREE, json.dumps(tree, separators=(",", ":")))
        for name, array in arrays.items():
            with zf.open(name + ".npy", "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(array), allow_pickle=False)
    return buf.getvalue()


def decode(data: bytes, allowed_modules: Iterable[str]) -> Any:
    """The object graph `encode` wrote; `StateCodecError` for anything else."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            tree = json.loads(zf.read(_TREE))
            arrays: dict[str, np.ndarray[Any, Any]] = {}
            for name in zf.namelist():
                if name.endswith(".npy"):
                    with zf.open(name) as f:
                        arrays[name[:-4]] = np.lib.format.read_array(f, allow_pickle=False)
    except (zipfile.BadZipFile, KeyError, ValueError, OSError, EOFError) as err:
        raise StateCodecError(f"not a state file: {err}") from err
    if not isinstance(tree, dict) or tree.get("format") != FORMAT:
        raise StateCodecError("unknown state format")
    try:
        return _Decoder(arrays, tuple(allowed_modules)).walk(tree["root"])
    except (TypeError, KeyError, AttributeError, ValueError, RecursionError) as err:
        if isinstance(err, StateCodecError):
            raise
        raise StateCodecError(f"state does not rebuild: {type(err).__name__}: {err}") from err


__all__ = ["StateCodecError", "decode", "encode"]

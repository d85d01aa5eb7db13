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
attribute), so existing compatibility hooks (`ScanMatcherFrontEnd.__setstate__`) keep working.
Shared references and cycles are kept, as pickle keeps them.

The bytes are an `.npz` (zip, deflate-compressed): `tree.json` plus one `.npy` per array, read
with `allow_pickle=False`.

With an `ArrayPack`, arrays that never change again (read-only and owning their data:
`service.core.types.frozen_array`, such as finished submaps and frozen map chunks) are not in
those bytes: each is appended to the pack file once, by the first checkpoint that holds it, and
every checkpoint refers to it by offset. So a checkpoint costs what changed since the last one,
not the whole session (a 1 km run with loop closure: 1.4 s and 25 MiB each time before).
"""

from __future__ import annotations

import base64
import collections
import copyreg
import enum
import hashlib
import importlib
import io
import json
import math
import os
import struct
import weakref
import zipfile
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Final

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


PACK_MAGIC: Final = b"MMPACK1\n"
_PACK_ENTRY = struct.Struct("<8sQ32s")  # magic, deflated length, sha256 of the deflated bytes
# Smaller frozen arrays stay in the checkpoint: an entry costs a header and a seek.
PACK_MIN_BYTES: Final = 1024
INLINE_ARRAY_BYTES: Final = 512  # arrays this small go in the JSON tree, not a `.npy` each

Array = np.ndarray[Any, Any]


class ArrayPack:
    """An append-only file of frozen arrays, each written once and referred to by offset.

    An entry is `PACK_MAGIC`, the deflated length, the sha256 of the deflated bytes, then the
    array's `.npy` bytes deflated. A reference is (offset, length, sha256 hex); reading checks
    all three, so a damaged or missing entry is a `StateCodecError` (the caller replays the
    recording instead). Appends are fsynced before `encode` returns: a checkpoint written
    after it never refers to bytes a power loss could take back. An entry cut by a crash is
    never referred to; later entries go after it.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        # id(array) -> (weak reference, its entry): each array object is written once.
        self._written: dict[int, tuple[weakref.ref[Array], list[Any]]] = {}
        self._end = 0  # where the last entry it remembers ends
        self._writer: IO[bytes] | None = None
        self._reader: IO[bytes] | None = None

    @staticmethod
    def takes(array: Array) -> bool:
        """Frozen (read-only, owning its data) and big enough to be worth an entry."""
        return not array.flags.writeable and array.base is None and array.nbytes >= PACK_MIN_BYTES

    def _known(self, array: Array) -> list[Any] | None:
        entry = self._written.get(id(array))
        if entry is not None and entry[0]() is array:
            return entry[1]
        return None

    def _remember(self, array: Array, ref: list[Any]) -> None:
        self._written[id(array)] = (weakref.ref(array), ref)
        self._end = max(self._end, ref[0] + _PACK_ENTRY.size + ref[1])

    def begin(self) -> None:
        """Before an encode: a file cut or replaced since (or gone) holds none of the entries
        this pack remembers, so they are written again rather than referred to."""
        try:
            size = self.path.stat().st_size
        except FileNotFoundError:
            size = 0
        if size < self._end:
            self._written.clear()
            self._end = 0

    def ref(self, array: Array) -> list[Any]:
        """The entry of `array`, appended now if this pack does not hold it yet."""
        known = self._known(array)
        if known is not None:
            return known
        buf = io.BytesIO()
        np.lib.format.write_array(buf, array, allow_pickle=False)
        data = zlib.compress(buf.getbuffer(), COMPRESS_LEVEL)
        digest = hashlib.sha256(data).digest()
        if self._writer is None:
            self._writer = open(self.path, "ab")  # noqa: SIM115  # closed by `sync`
        offset = self._writer.tell()
        self._writer.write(_PACK_ENTRY.pack(PACK_MAGIC, len(data), digest))
        self._writer.write(data)
        ref = [offset, len(data), digest.hex()]
        self._remember(array, ref)
        return ref

    def sync(self) -> None:
        """fsync what was appended (and the directory entry of a new file); forget the
        entries of arrays that are gone."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.flush()
                os.fsync(writer.fileno())
            finally:
                writer.close()
            fd = os.open(self.path.parent, os.O_RDONLY | os.O_DIRECTORY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        for key in [k for k, (w, _) in self._written.items() if w() is None]:
            del self._written[key]

    def load(self, ref: Any) -> Array:
        """The frozen array of entry `ref`, checked; this pack then knows it as written."""
        try:
            offset, length, digest_hex = int(ref[0]), int(ref[1]), str(ref[2])
            if self._reader is None:
                self._reader = open(self.path, "rb")  # noqa: SIM115  # closed by `done_reading`
            self._reader.seek(offset)
            head = self._reader.read(_PACK_ENTRY.size)
            magic, stored_length, digest = _PACK_ENTRY.unpack(head)
            data = self._reader.read(length)
        except (OSError, struct.error, TypeError, ValueError, IndexError) as err:
            raise StateCodecError(f"array pack entry unreadable: {err}") from err
        if magic != PACK_MAGIC or stored_length != length or len(data) != length:
            raise StateCodecError(f"array pack entry at {offset}: bad header or cut short")
        if digest != hashlib.sha256(data).digest() or digest.hex() != digest_hex:
            raise StateCodecError(f"array pack entry at {offset}: checksum mismatch")
        try:
            array = np.lib.format.read_array(io.BytesIO(zlib.decompress(data)), allow_pickle=False)
        except (ValueError, OSError, zlib.error) as err:
            raise StateCodecError(f"array pack entry at {offset}: {err}") from err
        if array.dtype.kind not in _ALLOWED_DTYPE_KINDS:
            raise StateCodecError(f"array pack entry of dtype {array.dtype} refused")
        array = array.copy() if array.base is not None else array
        array.flags.writeable = False
        self._remember(array, [offset, length, digest_hex])
        return array

    def done_reading(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            reader.close()


def _allowed(module: str, allowed: Iterable[str]) -> bool:
    return any(module == a or module.startswith(a + ".") for a in allowed)


@dataclass(frozen=True, slots=True)
class PackReport:
    """What `check_pack` found: intact entries, the first damage, a tail cut by a crash."""

    entries: int
    bytes_total: int
    damaged_at: int | None  # offset of the first entry that does not check out
    damage: str = ""
    torn_tail_bytes: int = 0


def check_pack(path: Path) -> PackReport:
    """Walk an array pack's entries and check each checksum (`fsck`)."""
    entries = 0
    with open(path, "rb") as f:
        total = os.fstat(f.fileno()).st_size
        offset = 0
        while offset < total:
            head = f.read(_PACK_ENTRY.size)
            if len(head) < _PACK_ENTRY.size:
                return PackReport(entries, total, None, torn_tail_bytes=total - offset)
            magic, length, digest = _PACK_ENTRY.unpack(head)
            if magic != PACK_MAGIC:
                return PackReport(entries, total, offset, "bad entry header")
            data = f.read(length)
            if len(data) < length:
                return PackReport(entries, total, None, torn_tail_bytes=total - offset)
            if hashlib.sha256(data).digest() != digest:
                return PackReport(entries, total, offset, "checksum mismatch")
            entries += 1
            offset += _PACK_ENTRY.size + length
    return PackReport(entries, total, None)


class _Encoder:
    def __init__(self, allowed: tuple[str, ...], pack: ArrayPack | None = None) -> None:
        self.allowed = allowed
        self.pack = pack
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
            if self.pack is not None and self.pack.takes(obj):
                return {"x": self.pack.ref(obj), "n": ref}
            if obj.nbytes <= INLINE_ARRAY_BYTES:
                # In the tree: a zip member each cost more than the tree itself (a long run's
                # graph holds thousands of 2x2 and 3x3 covariances).
                raw = np.ascontiguousarray(obj).tobytes()
                return {
                    "v": [obj.dtype.str, list(obj.shape), base64.b64encode(raw).decode()],
                    "n": ref,
                }
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
    def __init__(
        self,
        arrays: dict[str, np.ndarray[Any, Any]],
        allowed: tuple[str, ...],
        pack: ArrayPack | None = None,
    ) -> None:
        self.arrays = arrays
        self.allowed = allowed
        self.pack = pack
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
        elif "v" in node:
            value = _inline_array(node["v"])
        elif "x" in node:
            if self.pack is None:
                raise StateCodecError("the state refers to an array pack, and none was given")
            value = self.pack.load(node["x"])
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


def _inline_array(spec: Any) -> np.ndarray[Any, Any]:
    """An array the tree holds itself: [dtype, shape, base64 of its C-order bytes]."""
    dtype_str, shape, data = spec
    dtype = np.dtype(str(dtype_str))
    if dtype.kind not in _ALLOWED_DTYPE_KINDS:
        raise StateCodecError(f"numpy array of dtype {dtype} refused")
    flat = np.frombuffer(base64.b64decode(str(data)), dtype=dtype)
    return flat.reshape([int(n) for n in shape]).copy()


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


def encode(obj: object, allowed_modules: Iterable[str], pack: ArrayPack | None = None) -> bytes:
    """`obj` as compressed bytes; `StateCodecError` if the graph holds anything not allowed.

    With `pack`, frozen arrays go to it (once) and the bytes refer to them; they are fsynced
    before this returns."""
    encoder = _Encoder(tuple(allowed_modules), pack)
    if pack is not None:
        pack.begin()
    try:
        try:
            tree = {"format": FORMAT, "root": encoder.walk(obj)}
        finally:
            if pack is not None:
                pack.sync()
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


def decode(data: bytes, allowed_modules: Iterable[str], pack: ArrayPack | None = None) -> Any:
    """The object graph `encode` wrote (with the same `pack`, if it had one);
    `StateCodecError` for anything else."""
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
        return _Decoder(arrays, tuple(allowed_modules), pack).walk(tree["root"])
    except (TypeError, KeyError, AttributeError, ValueError, RecursionError) as err:
        if isinstance(err, StateCodecError):
            raise
        raise StateCodecError(f"state does not rebuild: {type(err).__name__}: {err}") from err
    finally:
        if pack is not None:
            pack.done_reading()


__all__ = ["ArrayPack", "PackReport", "StateCodecError", "check_pack", "decode", "encode"]

"""Read the tensors of a TorchScript archive without importing or executing anything from it.

Scaffold-GS saves its MLPs with ``torch.jit.trace(module, example).save(path)``. Such an archive
is a zip whose records all sit under one top folder ``<prefix>/``:

* ``data.pkl``: a pickle (protocol 2) of the module object. Modules are ``NEWOBJ`` of a
  ``__torch__.<qualified class>`` global followed by ``BUILD`` with a dict of attributes
  (submodules, parameters and buffers, ``training``, ...). A tensor is
  ``torch._utils._rebuild_tensor_v2(storage, offset, size, stride, requires_grad, hooks)`` where
  ``storage`` is a persistent id ``('storage', torch.<Type>Storage, key, location, numel)``.
* ``data/<key>``: the raw bytes of storage ``key``, in the byte order named by ``byteorder``
  (little-endian when that record is absent, as in archives of older torch versions).
* ``constants.pkl``, ``code/...`` (the TorchScript program), ``version``: not read here, except that
  ``constants.pkl`` tells a TorchScript archive from a ``torch.save`` file, which has none.

``torch.jit.load`` would compile and run the archive's code, and ``pickle`` would import and call
whatever globals ``data.pkl`` names. Neither is used. :func:`read_torchscript_state_dict` decodes
the opcode stream with :func:`pickletools.genops` (which only parses bytes) and interprets the few
opcodes that TorchScript writes with a small stack machine of its own: a global is kept as an
inert ``(module, name)`` pair and only accepted from an allowlist (the tensor rebuild function,
``collections.OrderedDict``, the numeric storage types, and ``__torch__.*`` module classes, which
exist only inside the archive); calls (``REDUCE``/``NEWOBJ``) and ``BUILD`` become symbolic nodes.
Nothing from the file is ever imported, called or instantiated. Tensors are then built from the
storage bytes with :func:`torch.frombuffer` and :func:`torch.as_strided` after bounds checks.

The result is a flat state dict named as ``module.state_dict()`` names it (``0.weight``,
``embedding.weight``, ...). ``data.pkl`` does not say which tensor attributes are parameters or
buffers (that is in the archive's code), so every tensor attribute of every module is returned;
for the modules Scaffold-GS saves these are exactly the state dict.
"""

from __future__ import annotations

import io
import os
from pickletools import genops  # parses opcodes; unlike pickle it never builds objects
import zipfile
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

__all__ = ["TorchScriptError", "archive_kind", "read_torchscript_state_dict"]


class TorchScriptError(ValueError):
    """The archive is not a TorchScript archive this reader accepts; the message says why."""


# torch.<name> storage type -> element dtype. Only plain numeric types; anything else is refused.
STORAGE_DTYPES = {
    "FloatStorage": torch.float32,
    "DoubleStorage": torch.float64,
    "HalfStorage": torch.float16,
    "BFloat16Storage": torch.bfloat16,
    "LongStorage": torch.int64,
    "IntStorage": torch.int32,
    "ShortStorage": torch.int16,
    "CharStorage": torch.int8,
    "ByteStorage": torch.uint8,
}
_REBUILD_TENSOR = ("torch._utils", "_rebuild_tensor_v2")
_ORDERED_DICT = ("collections", "OrderedDict")
# A module class of a TorchScript archive is named by the archive's own code, under this package;
# it is never looked up, so any name below it is accepted as a symbol.
_MODULE_CLASS_PACKAGE = "__torch__"
MAX_PICKLE_BYTES = 64 << 20
MAX_MODULE_DEPTH = 64
# Submodules walked in all: the pickle's memo lets a module refer to one child twice, so a file of a
# few kilobytes could otherwise be walked 2^depth times.
MAX_MODULES = 4096
MAX_TENSOR_DIMS = 64


@dataclass(frozen=True)
class Global:
    """A global named by the pickle; a symbol only, never imported."""

    module: str
    name: str

    def __str__(self) -> str:
        return f"{self.module}.{self.name}"


@dataclass(frozen=True)
class StorageRef:
    """A ``BINPERSID`` storage reference: ``('storage', type, key, location, numel)``."""

    dtype: torch.dtype
    key: str
    location: str
    numel: int


@dataclass(eq=False)
class Call:
    """``REDUCE`` (``func(*args)``) or ``NEWOBJ`` (``cls.__new__(cls, *args)``), not performed;
    ``state`` is what a later ``BUILD`` would have set on the result."""

    func: Global
    args: tuple
    newobj: bool
    state: Any = None
    built: bool = field(default=False)


class _Mark:
    """The MARK sentinel on the stack."""


_MARK = _Mark()


def archive_kind(path: str | os.PathLike) -> str | None:
    """``"torchscript"`` (a ``torch.jit.save`` archive), ``"torch.save"`` (a zip ``torch.save``
    file), ``"zip"`` (any other zip) or None (not a zip).

    Both torch formats keep their records under one top folder with a ``data.pkl``; only
    TorchScript writes ``constants.pkl`` (the test torch itself uses to tell them apart).
    """
    if not zipfile.is_zipfile(path):
        return None
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
    except (zipfile.BadZipFile, OSError, ValueError):
        return "zip"
    try:
        prefix = _prefix(names)
    except TorchScriptError:
        return "zip"
    if f"{prefix}/constants.pkl" in names:
        return "torchscript"
    return "torch.save"


def _prefix(names: list[str]) -> str:
    prefixes = {name.split("/", 1)[0] for name in names if "/" in name}
    candidates = [p for p in prefixes if f"{p}/data.pkl" in names]
    if len(candidates) != 1:
        raise TorchScriptError(f"expected one '<prefix>/data.pkl' record, found {len(candidates)}")
    return candidates[0]


def read_torchscript_state_dict(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The named tensors of the TorchScript archive at ``path``, as ``state_dict()`` names them.

    Tensors are on the CPU, whatever location the archive records. Raises
    :class:`TorchScriptError` for anything that is not a well-formed archive of this kind: a
    global outside the allowlist, an opcode TorchScript does not write, a truncated pickle, a
    storage whose record is missing or of the wrong size, a tensor reaching outside its storage.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            prefix = _prefix(names)
            if f"{prefix}/constants.pkl" not in names:
                raise TorchScriptError("has no constants.pkl: not a TorchScript archive")
            info = archive.getinfo(f"{prefix}/data.pkl")
            if info.file_size > MAX_PICKLE_BYTES:
                raise TorchScriptError(f"data.pkl is {info.file_size} bytes; more than {MAX_PICKLE_BYTES} is refused")
            root = interpret_pickle(archive.read(info))
            big_endian = False
            if f"{prefix}/byteorder" in names:
                order = archive.read(f"{prefix}/byteorder")[:16].decode("ascii", "replace").strip()
                if order not in ("little", "big"):
                    raise TorchScriptError(f"byteorder record says {order!r}; expected 'little' or 'big'")
                big_endian = order == "big"
            storages = _StorageReader(archive, prefix, big_endian)
            if not _is_module(root):
                raise TorchScriptError(f"data.pkl holds {_describe(root)}, not a module")
            state: dict[str, torch.Tensor] = {}
            _collect(root, "", state, storages, depth=0, walked=[0])
            return state
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, OSError) as e:
        raise TorchScriptError(f"unreadable zip archive ({e})") from e


# ----------------------------------------------------------------------------------------------
# The pickle stack machine
# ----------------------------------------------------------------------------------------------

_PUSH_ARG = {
    # opcode -> its decoded argument is the pushed value
    "INT", "BININT", "BININT1", "BININT2", "LONG", "LONG1", "LONG4",
    "FLOAT", "BINFLOAT",
    "UNICODE", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8",
}
_CONSTANTS = {"NONE": None, "NEWTRUE": True, "NEWFALSE": False}


def interpret_pickle(data: bytes) -> Any:
    """Evaluate a TorchScript ``data.pkl`` symbolically and return its top object.

    Only the opcodes TorchScript's pickler emits are interpreted; globals become :class:`Global`
    symbols (allowlisted), calls :class:`Call` nodes and storages :class:`StorageRef` values.
    """
    stack: list[Any] = []
    marks: list[int] = []
    memo: dict[int, Any] = {}

    def pop_mark() -> list[Any]:
        if not marks:
            raise TorchScriptError("data.pkl pops a MARK that was never set")
        start = marks.pop()
        items = stack[start:]
        del stack[start:]
        return items

    def pop() -> Any:
        if not stack or (marks and len(stack) <= marks[-1]):
            raise TorchScriptError("data.pkl pops from an empty stack")
        return stack.pop()

    def top() -> Any:
        if not stack or (marks and len(stack) <= marks[-1]):
            raise TorchScriptError("data.pkl reads from an empty stack")
        return stack[-1]

    try:
        for opcode, arg, pos in genops(io.BytesIO(data)):
            name = opcode.name
            if name in _PUSH_ARG:
                stack.append(arg)
            elif name in _CONSTANTS:
                stack.append(_CONSTANTS[name])
            elif name in ("PROTO", "FRAME"):
                if name == "PROTO" and not 2 <= arg <= 5:
                    raise TorchScriptError(f"data.pkl is pickle protocol {arg}; TorchScript writes 2")
            elif name == "MARK":
                marks.append(len(stack))
            elif name in ("PUT", "BINPUT", "LONG_BINPUT"):
                memo[int(arg)] = top()
            elif name == "MEMOIZE":
                memo[len(memo)] = top()
            elif name in ("GET", "BINGET", "LONG_BINGET"):
                if int(arg) not in memo:
                    raise TorchScriptError(f"data.pkl reads memo entry {arg} at byte {pos} before writing it")
                stack.append(memo[int(arg)])
            elif name == "EMPTY_TUPLE":
                stack.append(())
            elif name in ("TUPLE1", "TUPLE2", "TUPLE3"):
                n = int(name[-1])
                items = [pop() for _ in range(n)][::-1]
                stack.append(tuple(items))
            elif name == "TUPLE":
                stack.append(tuple(pop_mark()))
            elif name == "EMPTY_LIST":
                stack.append([])
            elif name == "LIST":
                stack.append(pop_mark())
            elif name == "EMPTY_DICT":
                stack.append({})
            elif name == "DICT":
                items = pop_mark()
                stack.append(_pairs_into({}, items, pos))
            elif name == "APPEND":
                value = pop()
                _expect(top(), list, "APPEND", pos).append(value)
            elif name == "APPENDS":
                items = pop_mark()
                _expect(top(), list, "APPENDS", pos).extend(items)
            elif name == "SETITEM":
                value = pop()
                key = pop()
                _pairs_into(_expect(top(), dict, "SETITEM", pos), [key, value], pos)
            elif name == "SETITEMS":
                items = pop_mark()
                _pairs_into(_expect(top(), dict, "SETITEMS", pos), items, pos)
            elif name == "GLOBAL":
                module, _, qualname = arg.partition(" ")
                stack.append(_allowed_global(module, qualname, pos))
            elif name == "STACK_GLOBAL":
                qualname = pop()
                module = pop()
                if not isinstance(module, str) or not isinstance(qualname, str):
                    raise TorchScriptError(f"STACK_GLOBAL at byte {pos} names a global with non-strings")
                stack.append(_allowed_global(module, qualname, pos))
            elif name == "BINPERSID":
                stack.append(_storage_ref(pop(), pos))
            elif name in ("REDUCE", "NEWOBJ"):
                args = pop()
                func = pop()
                if not isinstance(func, Global) or not isinstance(args, tuple):
                    raise TorchScriptError(f"{name} at byte {pos} applies {_describe(func)} to {_describe(args)}")
                newobj = name == "NEWOBJ"
                if newobj != func.module.startswith(_MODULE_CLASS_PACKAGE):
                    raise TorchScriptError(f"{name} at byte {pos} of {func} is not how TorchScript writes it")
                stack.append(Call(func, args, newobj))
            elif name == "BUILD":
                state = pop()
                obj = top()
                if not isinstance(obj, Call) or not obj.newobj or obj.built:
                    raise TorchScriptError(f"BUILD at byte {pos} on {_describe(obj)}")
                obj.state, obj.built = state, True
            elif name == "STOP":
                if marks or len(stack) != 1:
                    raise TorchScriptError(f"data.pkl stops with {len(stack)} values and {len(marks)} marks "
                                           "on the stack; expected one value")
                return stack[0]
            else:
                raise TorchScriptError(f"data.pkl uses pickle opcode {name} at byte {pos}, which TorchScript "
                                       "archives do not contain")
    except ValueError as e:
        if isinstance(e, TorchScriptError):
            raise
        # pickletools raises ValueError for unknown opcodes and for a stream without STOP.
        raise TorchScriptError(f"data.pkl is not a complete pickle ({e})") from e
    raise TorchScriptError("data.pkl ends without STOP (truncated)")


def _allowed_global(module: str, name: str, pos: int) -> Global:
    symbol = Global(module, name)
    if (module, name) in (_REBUILD_TENSOR, _ORDERED_DICT):
        return symbol
    if module == "torch" and name in STORAGE_DTYPES:
        return symbol
    if module == _MODULE_CLASS_PACKAGE or module.startswith(_MODULE_CLASS_PACKAGE + "."):
        return symbol
    raise TorchScriptError(f"data.pkl names the global {module}.{name} at byte {pos}; only TorchScript "
                           "module classes, torch storage types, torch._utils._rebuild_tensor_v2 and "
                           "collections.OrderedDict are accepted (nothing is imported or called)")


def _storage_ref(pid: Any, pos: int) -> StorageRef:
    if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
        raise TorchScriptError(f"BINPERSID at byte {pos} references {_describe(pid)}, not "
                               "('storage', type, key, location, numel)")
    _, storage_type, key, location, numel = pid
    if not (isinstance(storage_type, Global) and storage_type.module == "torch"
            and storage_type.name in STORAGE_DTYPES):
        raise TorchScriptError(f"storage at byte {pos} has type {_describe(storage_type)}")
    if not (isinstance(key, str) and key and "/" not in key and key not in (".", "..")):
        raise TorchScriptError(f"storage at byte {pos} has key {key!r}")
    if not isinstance(location, str) or not _is_int(numel) or numel < 0:
        raise TorchScriptError(f"storage {key!r} has location {location!r} and size {numel!r}")
    return StorageRef(STORAGE_DTYPES[storage_type.name], key, location, numel)


def _pairs_into(target: dict, items: list, pos: int) -> dict:
    if len(items) % 2:
        raise TorchScriptError(f"dict items at byte {pos} are not key/value pairs")
    for key, value in zip(items[::2], items[1::2]):
        try:
            target[key] = value
        except TypeError as e:
            raise TorchScriptError(f"dict key at byte {pos} is {_describe(key)} ({e})") from e
    return target


def _expect(value: Any, kind: type, opcode: str, pos: int) -> Any:
    if not isinstance(value, kind):
        raise TorchScriptError(f"{opcode} at byte {pos} applies to {_describe(value)}, not a {kind.__name__}")
    return value


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _describe(value: Any) -> str:
    if isinstance(value, Call):
        return f"a call of {value.func}"
    if isinstance(value, Global):
        return f"the global {value}"
    if isinstance(value, StorageRef):
        return f"storage {value.key!r}"
    return f"a value of type {type(value).__name__}"


# ----------------------------------------------------------------------------------------------
# From the symbolic tree to tensors
# ----------------------------------------------------------------------------------------------


def _is_module(value: Any) -> bool:
    return isinstance(value, Call) and value.newobj and isinstance(value.state, dict)


def _is_tensor(value: Any) -> bool:
    return isinstance(value, Call) and not value.newobj and (value.func.module, value.func.name) == _REBUILD_TENSOR


def _collect(module: Call, prefix: str, out: dict[str, torch.Tensor], storages: "_StorageReader",
             depth: int, walked: list[int]) -> None:
    """Every tensor of ``module`` and its submodules into ``out`` by dotted name; ``walked`` [1]
    counts the modules walked so far, over the whole archive."""
    if depth > MAX_MODULE_DEPTH:
        raise TorchScriptError(f"modules nest deeper than {MAX_MODULE_DEPTH} levels at '{prefix}'")
    walked[0] += 1
    if walked[0] > MAX_MODULES:
        raise TorchScriptError(f"more than {MAX_MODULES} modules to walk (at '{prefix}'): an MLP file has a few")
    for key, value in module.state.items():
        if not isinstance(key, str):
            continue
        name = f"{prefix}{key}"
        if _is_tensor(value):
            out[name] = _build_tensor(name, value, storages)
        elif _is_module(value):
            _collect(value, f"{name}.", out, storages, depth + 1, walked)
        # Anything else (training flags, hooks, ints, None for an absent bias) is not a tensor.


def _build_tensor(name: str, call: Call, storages: "_StorageReader") -> torch.Tensor:
    args = call.args
    if len(args) < 4:
        raise TorchScriptError(f"tensor '{name}' is rebuilt from {len(args)} arguments; expected at least 4")
    storage, offset, size, stride = args[:4]
    if not isinstance(storage, StorageRef):
        raise TorchScriptError(f"tensor '{name}' is rebuilt from {_describe(storage)}, not a storage")
    if not (isinstance(size, tuple) and isinstance(stride, tuple) and len(size) == len(stride)
            and len(size) <= MAX_TENSOR_DIMS and all(_is_int(v) and v >= 0 for v in size + stride)
            and _is_int(offset) and offset >= 0):
        raise TorchScriptError(f"tensor '{name}' has offset {offset!r}, size {size!r}, stride {stride!r}")
    numel = int(np.prod(size, dtype=object)) if size else 1
    if numel > 0:
        last = offset + sum((n - 1) * s for n, s in zip(size, stride))
        if last >= storage.numel:
            raise TorchScriptError(f"tensor '{name}' reaches element {last} of storage {storage.key!r}, "
                                   f"which has {storage.numel}")
        if numel > storage.numel:
            raise TorchScriptError(f"tensor '{name}' has {numel} elements from a storage of {storage.numel}")
    flat = storages.get(storage)
    return torch.as_strided(flat, size, stride, offset).clone()


class _StorageReader:
    """Storages by key, each read once from ``<prefix>/data/<key>``."""

    def __init__(self, archive: zipfile.ZipFile, prefix: str, big_endian: bool):
        self.archive, self.prefix, self.big_endian = archive, prefix, big_endian
        self.cache: dict[str, torch.Tensor] = {}

    def get(self, ref: StorageRef) -> torch.Tensor:
        if ref.key in self.cache:
            cached = self.cache[ref.key]
            if cached.dtype != ref.dtype or cached.numel() != ref.numel:
                raise TorchScriptError(f"storage {ref.key!r} is referenced with two different types or sizes")
            return cached
        record = f"{self.prefix}/data/{ref.key}"
        try:
            info = self.archive.getinfo(record)
        except KeyError:
            raise TorchScriptError(f"storage record {record} is missing") from None
        itemsize = torch.empty((), dtype=ref.dtype).element_size()
        if info.file_size != ref.numel * itemsize:
            raise TorchScriptError(f"storage record {record} has {info.file_size} bytes; "
                                   f"{ref.numel} x {itemsize} expected")
        if info.compress_type != zipfile.ZIP_STORED:
            # torch.jit.save stores tensor data uncompressed; a compressed record could expand a
            # small file into a large allocation.
            raise TorchScriptError(f"storage record {record} is compressed; torch writes it stored")
        raw = bytearray(self.archive.read(info))
        if ref.numel == 0:
            flat = torch.empty(0, dtype=ref.dtype)
        else:
            if self.big_endian and itemsize > 1:
                raw = bytearray(np.frombuffer(raw, dtype=np.uint8).reshape(-1, itemsize)[:, ::-1].tobytes())
            flat = torch.frombuffer(raw, dtype=ref.dtype)
        self.cache[ref.key] = flat
        return flat

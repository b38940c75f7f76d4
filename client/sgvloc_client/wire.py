"""The binary wire format shared by the service and the SDK.

Request and response bodies are either JSON (``application/json``; arrays as nested
lists, fine for small requests and curl) or MessagePack (``application/msgpack``) with
the *same* structure, where every array is a map

    {"__nd__": True, "dtype": "<f4", "shape": [P, 4], "data": <raw little-endian bytes>}

so a 120k-point scan travels as 1.9 MB of float32 instead of megabytes of JSON digits.
Allowed dtypes: little-endian float32/float64/int32/int64/uint8. Decoding checks that
``data`` holds exactly ``prod(shape) * itemsize`` bytes and names the offending field.
"""

from __future__ import annotations

import math
from typing import Any

import msgpack
import numpy as np

MSGPACK = "application/msgpack"
JSON = "application/json"
ALLOWED_DTYPES = ("<f4", "<f8", "<i4", "<i8", "|u1")
MAX_NDIM = 4


class WireError(ValueError):
    """A body cannot be decoded; the message names the field and the problem, and
    ``field`` the request field when one is at fault (``keyframes[3].points``)."""

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


def encode_array(arr: np.ndarray) -> dict[str, Any]:
    """An ndarray as a MessagePack-ready map (little-endian, C order)."""
    a = np.asarray(arr)
    kind, size = a.dtype.kind, a.dtype.itemsize
    if kind == "f":
        a = a.astype("<f8" if size == 8 else "<f4", copy=False)
    elif kind == "b" or (kind == "u" and size == 1):
        a = a.astype("|u1", copy=False)
    elif kind == "i" or (kind == "u" and size < 8):
        # every value kept: int8/16 and uint16 fit int32, uint32 needs int64
        a = a.astype("<i8" if size == 8 or (kind == "u" and size == 4) else "<i4", copy=False)
    elif kind == "u":  # uint64: as int64 where every value fits
        if a.size and int(a.max()) > np.iinfo(np.int64).max:
            raise ValueError("a uint64 array with values beyond int64 cannot be sent")
        a = a.astype("<i8", copy=False)
    else:
        raise ValueError(f"arrays of dtype {a.dtype} cannot be sent (numbers only)")
    a = np.ascontiguousarray(a)
    return {"__nd__": True, "dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def decode_array(obj: dict[str, Any], where: str = "array") -> np.ndarray:
    """Inverse of :func:`encode_array`; raises :class:`WireError` on any inconsistency."""
    field = where.removeprefix("body.") if where.startswith("body.") else None
    dtype, shape, data = obj.get("dtype"), obj.get("shape"), obj.get("data")
    if dtype not in ALLOWED_DTYPES:
        raise WireError(
            f"{where}: dtype {dtype!r} not allowed (use one of {ALLOWED_DTYPES})", field
        )
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_NDIM
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)
    ):
        raise WireError(
            f"{where}: shape must be a list of at most {MAX_NDIM} non-negative ints", field
        )
    if not isinstance(data, bytes | bytearray):
        raise WireError(f"{where}: data must be bytes", field)
    # Python integers: a shape such as [2**62, 4] or [2**64 - 1] must not wrap around
    expected = math.prod(shape) * np.dtype(dtype).itemsize
    if len(data) != expected:
        raise WireError(
            f"{where}: data has {len(data)} bytes but shape {shape} of {dtype} needs {expected}",
            field,
        )
    return np.frombuffer(data, dtype=dtype).reshape(shape)


def _to_wire(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return encode_array(obj)
    if isinstance(obj, dict):
        return {k: _to_wire(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_to_wire(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _from_wire(obj: Any, where: str = "body") -> Any:
    if isinstance(obj, dict):
        if obj.get("__nd__") is True:
            return decode_array(obj, where)
        return {k: _from_wire(v, f"{where}.{k}") for k, v in obj.items()}
    if isinstance(obj, list):
        if not any(isinstance(v, dict | list) for v in obj):  # numbers: nothing inside
            return obj
        return [_from_wire(v, f"{where}[{i}]") for i, v in enumerate(obj)]
    return obj


def packb(obj: Any) -> bytes:
    """Serialise a structure (dicts, lists, scalars, ndarrays) to MessagePack."""
    return msgpack.packb(_to_wire(obj), use_bin_type=True)


#: a MessagePack body may hold one map or list per this many bytes (an array travels as
#: one map with its bytes; a list of three float32 takes 16)
MSGPACK_BYTES_PER_CONTAINER = 12


def container_budget(size: int, bytes_per_container: int) -> int:
    """How many maps and lists (objects and arrays) a body of ``size`` bytes may hold:
    an empty one takes a byte or two in the body and tens of bytes in memory, so a body
    of little else would cost a hundred times its size to parse."""
    return size // bytes_per_container + 10_000


def unpackb(
    data: bytes,
    max_bytes: int | None = None,
    max_list_len: int | None = None,
    *,
    max_map_len: int | None = None,
    max_containers: int | None = None,
) -> Any:
    """Parse MessagePack into the same structure with ndarrays restored (read-only views).
    Refuses a body holding more maps and lists than :func:`container_budget` allows (and
    than ``max_containers``), a list of more than ``max_list_len`` items or a map of more
    than ``max_map_len`` keys."""
    if max_bytes is not None and len(data) > max_bytes:
        raise WireError(f"body has {len(data)} bytes, limit is {max_bytes}")
    budget = container_budget(len(data), MSGPACK_BYTES_PER_CONTAINER)
    if max_containers is not None:
        budget = min(budget, max_containers)
    count = 0

    def counted(container: Any) -> Any:
        nonlocal count
        count += 1
        if count > budget:
            raise WireError(
                f"body holds more than {budget} maps and lists in {len(data)} bytes: too "
                "many to be a request (arrays travel as bytes, a few fields each)"
            )
        return container

    try:
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            object_hook=counted,
            list_hook=counted,
            max_array_len=len(data) if max_list_len is None else max_list_len,
            max_map_len=len(data) if max_map_len is None else max_map_len,
        )
    except WireError:
        raise
    except (msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, ValueError) as exc:
        if "max_array_len" in str(exc):
            raise WireError(
                f"body holds a list of more than {max_list_len} items: longer than any field"
            ) from None
        if "max_map_len" in str(exc):
            raise WireError(
                f"body holds a map of more than {max_map_len} keys: more than any object has"
            ) from None
        if isinstance(exc, msgpack.StackError):
            raise WireError("body is not valid MessagePack: nested too deeply") from None
        why = str(exc) or type(exc).__name__
        raise WireError(f"body is not valid MessagePack: {why}") from None
    return _from_wire(obj)


def to_jsonable(obj: Any) -> Any:
    """The JSON form of the same structure: arrays become nested lists."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, dict):
        return {k: to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj

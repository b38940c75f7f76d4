"""Request bodies in, responses out: JSON or MessagePack (see ``sgvloc_client.wire``).

- :func:`read_body` reads the raw bytes with a size limit (413 beyond it, checked against
  ``Content-Length`` first and then while streaming) and refuses other media types (415);
- :meth:`RawBody.decode` parses them (400 on undecodable or truncated bodies). It is
  CPU work on large bodies, so routes call it in the worker threads, not on the loop;
- :func:`encode` writes a response as the ``Accept`` header asks: MessagePack (transforms,
  translations and quaternions as float64 arrays) or JSON (the default).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import anyio
import numpy as np
from fastapi import Request
from fastapi.responses import Response
from pydantic import BaseModel
from starlette.requests import ClientDisconnect

from sgvloc_client import wire

from .errors import ApiError

MSGPACK_TYPES = (wire.MSGPACK, "application/x-msgpack", "application/vnd.msgpack")
JSON_TYPES = (wire.JSON,)

#: a JSON body may hold one object or array per this many bytes (a point [0,0,0], is 8)
JSON_BYTES_PER_CONTAINER = 6
#: the most fields an object (JSON) or map (MessagePack) of a body may have: far above any
#: request's (tags: 64); each unknown field would otherwise cost a validation error
MAX_OBJECT_FIELDS = 256
#: MessagePack carries arrays as bytes: a body holds a few maps and lists per keyframe
MSGPACK_CONTAINERS_PER_ITEM = 32


def _object(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object, refused beyond :data:`MAX_OBJECT_FIELDS` fields (the last of a
    repeated field wins, as ``json.loads`` has it)."""
    if len(pairs) > MAX_OBJECT_FIELDS:
        raise wire.WireError(
            f"body holds an object of {len(pairs)} fields: more than any object of a "
            f"request has ({MAX_OBJECT_FIELDS})"
        )
    return dict(pairs)


#: numeric response fields sent as ndarrays in MessagePack (float64)
ARRAY_FIELDS = frozenset({"T_map_sensor", "T_keyframe_sensor", "translation", "quaternion_xyzw"})


class BodyBudget:
    """The bytes of request bodies held in memory at once, over all requests, within
    ``limit`` (``max_body_memory_bytes``). Used on the event loop only: a plain counter."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.used = 0

    def take(self, n: int) -> bool:
        """Reserve ``n`` more bytes; False (nothing reserved) if that passes the limit."""
        if self.used + n > self.limit:
            return False
        self.used += n
        return True

    def give_back(self, n: int) -> None:
        self.used -= n


class BodyHold:
    """One request's share of a :class:`BodyBudget`, given back by :meth:`close`."""

    def __init__(self, budget: BodyBudget) -> None:
        self.budget = budget
        self.held = 0

    def grow_to(self, n: int, *, started: bool) -> None:
        """Hold ``n`` bytes in all, or 503 ``overloaded`` (closing the connection once part
        of the body has been read) when the budget has no room."""
        if n <= self.held:
            return
        if not self.budget.take(n - self.held):
            raise ApiError(
                503,
                "overloaded",
                f"request bodies in memory take {self.budget.used} of "
                f"max_body_memory_bytes={self.budget.limit} bytes, no room for {n} more; "
                "retry later",
                headers={"Retry-After": "1", **({"Connection": "close"} if started else {})},
            )
        self.held = n

    def close(self) -> None:
        self.budget.give_back(self.held)
        self.held = 0


def media_type(header: str | None) -> str:
    """The bare, lower-case media type of a Content-Type header."""
    return (header or "").split(";")[0].strip().lower()


@dataclass(frozen=True)
class RawBody:
    """A request body read within the size limit, not parsed yet."""

    data: bytes
    content_type: str
    #: longest list (MessagePack) a body may hold; None: no bound
    max_list_len: int | None = None
    #: the most maps and lists (MessagePack) a body may hold; None: by its size only
    max_containers: int | None = None

    def decode(self) -> Any:
        """Parse the body; arrays become ndarrays (MessagePack) or nested lists (JSON)."""
        if not self.data:
            raise ApiError(400, "bad_body", "the request body is empty")
        try:
            if self.content_type in MSGPACK_TYPES:
                return wire.unpackb(
                    self.data,
                    max_list_len=self.max_list_len,
                    max_map_len=MAX_OBJECT_FIELDS,
                    max_containers=self.max_containers,
                )
            # each object or array costs tens of bytes in memory however few it takes in
            # the body ("{}," is three): a body of little else is refused before parsing
            n = self.data.count(b"{") + self.data.count(b"[")
            if n > wire.container_budget(len(self.data), JSON_BYTES_PER_CONTAINER):
                raise ApiError(
                    400,
                    "bad_body",
                    f"the body holds {n} objects and arrays in {len(self.data)} bytes: too "
                    "many to be a request (arrays of numbers, a few fields each)",
                )
            return json.loads(self.data, object_pairs_hook=_object)
        except wire.WireError as exc:
            raise ApiError(400, "bad_body", str(exc), exc.field) from None
        except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
            raise ApiError(400, "bad_body", f"body is not valid JSON: {exc}") from None
        except (RecursionError, TypeError) as exc:
            raise ApiError(400, "bad_body", f"body cannot be decoded: {exc}") from None


async def read_body(
    request: Request,
    limit: int,
    timeout_s: float | None = None,
    *,
    json_limit: int | None = None,
    max_list_len: int | None = None,
    max_items: int | None = None,
    hold: BodyHold | None = None,
) -> RawBody:
    """Read the whole body, at most ``limit`` bytes (``json_limit`` for JSON) within
    ``timeout_s`` seconds; 415 for a media type other than JSON or MessagePack, 413
    beyond the limit, 408 (and the connection closed) when the body is not complete in
    time, 400 when the client goes away before it is. ``max_items``: the most items (e.g.
    keyframes) a body may carry, which bounds the maps and lists of a MessagePack one.
    ``hold``: the process's room for bodies, taken for the declared length before any
    byte is read and as the body grows (503 ``overloaded`` when there is none); the
    caller gives it back once the request is done."""
    ctype = media_type(request.headers.get("content-type"))
    if ctype not in MSGPACK_TYPES + JSON_TYPES:
        raise ApiError(
            415,
            "unsupported_media_type",
            f"Content-Type {ctype or '(none)'!r} is not supported: send "
            f"{wire.JSON!r} or {wire.MSGPACK!r}",
        )
    what = "the limit"
    if ctype in JSON_TYPES and json_limit is not None and json_limit < limit:
        limit, what = json_limit, "the limit for JSON (send MessagePack for large bodies)"
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise ApiError(
            413, "payload_too_large", f"body has {int(declared)} bytes, {what} is {limit}"
        )
    if hold is not None and declared is not None and declared.isdigit():
        hold.grow_to(int(declared), started=False)
    buf = bytearray()
    with anyio.move_on_after(timeout_s) as scope:
        try:
            async for chunk in request.stream():
                buf += chunk
                if len(buf) > limit:
                    raise ApiError(
                        413, "payload_too_large", f"body exceeds {what} of {limit} bytes"
                    )
                if hold is not None:
                    hold.grow_to(len(buf), started=True)
        except ClientDisconnect:  # nobody to answer: not the service's error
            raise ApiError(
                400, "bad_body", "the client closed the connection before the body was complete"
            ) from None
    if scope.cancelled_caught:
        raise ApiError(
            408,
            "request_timeout",
            f"the body did not arrive within body_timeout_s={timeout_s:g} s",
            headers={"Connection": "close"},
        )
    containers = None if max_items is None else 10_000 + MSGPACK_CONTAINERS_PER_ITEM * max_items
    return RawBody(bytes(buf), ctype, max_list_len, containers)


def wants_msgpack(request: Request) -> bool:
    """True if the client's ``Accept`` header asks for MessagePack."""
    accept = request.headers.get("accept", "").lower()
    return any(t in accept for t in MSGPACK_TYPES)


def _as_f8(value: Any) -> np.ndarray:
    return np.asarray(value, dtype=np.float64)


def _arrays(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {
            k: np.asarray(v, dtype=np.float64)
            if k in ARRAY_FIELDS and v is not None
            else _arrays(v)
            for k, v in obj.items()
        }
    if isinstance(obj, list):
        return [_arrays(v) for v in obj]
    return obj


def encode(request: Request, payload: BaseModel | dict[str, Any], status: int = 200) -> Response:
    """A response with ``payload`` in the format the request's ``Accept`` asks for."""
    if wants_msgpack(request):
        data = payload.model_dump() if isinstance(payload, BaseModel) else payload
        return Response(wire.packb(_arrays(data)), status_code=status, media_type=wire.MSGPACK)
    if isinstance(payload, BaseModel):
        content = payload.model_dump_json().encode()
    else:
        content = json.dumps(wire.to_jsonable(payload), allow_nan=False).encode()
    return Response(content, status_code=status, media_type=wire.JSON)

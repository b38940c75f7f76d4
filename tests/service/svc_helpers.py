"""Helpers of the service tests (requests, errors, poses, synthetic features)."""

from __future__ import annotations

import socket
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np

from sgvloc.core.sequence import KittiSequence
from sgvloc_client import wire

#: limits of the test server (set through SGVLOC_* by conftest.py)
MAX_BODY_BYTES = 8 * 1024 * 1024
MAX_POINTS = 60_000
MAX_BATCH = 20
MAX_TOP_K = 50


# -- request helpers -----------------------------------------------------------------------


def post_msgpack(
    c: httpx.Client, path: str, body: Any, headers: dict[str, str] | None = None
) -> httpx.Response:
    """POST ``body`` as MessagePack (arrays as raw little-endian bytes)."""
    return c.post(
        path, content=wire.packb(body), headers={"Content-Type": wire.MSGPACK, **(headers or {})}
    )


def answer_head(sock: socket.socket, timeout: float = 30) -> str:
    """The status line and headers of the answer on a raw socket, lower case ("" when
    the connection closes before them)."""
    sock.settimeout(timeout)
    answer = b""
    while b"\r\n\r\n" not in answer:
        chunk = sock.recv(4096)
        if not chunk:
            break
        answer += chunk
    return answer.split(b"\r\n\r\n")[0].decode().lower()


def decode(r: httpx.Response) -> Any:
    """A response body by its Content-Type."""
    if r.headers.get("content-type", "").startswith(wire.MSGPACK):
        return wire.unpackb(r.content)
    return r.json()


def error_of(r: httpx.Response) -> dict[str, Any]:
    """The ``error`` object of an error response (checks the documented shape)."""
    body = r.json()
    assert set(body) == {"error"}, body
    err = body["error"]
    assert set(err) == {"code", "message", "field"}, err
    assert err["message"], err
    return err


def map_state(c: httpx.Client, name: str) -> tuple[int, int]:
    """``(keyframes, version)`` of a map."""
    r = c.get(f"/v1/maps/{name}")
    assert r.status_code == 200, r.text
    info = r.json()
    return info["keyframes"], info["version"]


def rotation_z(yaw: float) -> np.ndarray:
    """A 4x4 rotation about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) error between two poses."""
    D = np.linalg.inv(T_true) @ np.asarray(T_est)
    cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(np.arccos(cos)))


def random_features(
    rng: np.random.Generator, n: int = 64, g: int = 16, d: int = 8
) -> dict[str, np.ndarray]:
    """Features for a precomputed map: keypoints spread over 40 m, distinct features."""
    return {
        "global_descriptor": rng.normal(size=g).astype(np.float32),
        "keypoints": rng.uniform(-20, 20, size=(n, 3)).astype(np.float32),
        "local_features": rng.normal(size=(n, d)).astype(np.float32),
    }


def feature_keyframes(
    rng: np.random.Generator,
    n: int,
    key_prefix: str | None = None,
    metadata: dict[str, Any] | None = None,
) -> list:
    """``n`` keyframes of :func:`random_features` for the map manager, keyframe ``i`` at
    x = i m, keyed ``<key_prefix><i>`` when a prefix is given."""
    from sgvloc.server.maps import FeaturesIn, KeyframeIn

    out = []
    for i in range(n):
        f = random_features(rng)
        T = np.eye(4)
        T[:3, 3] = [float(i), 0.0, 0.0]
        out.append(
            KeyframeIn(
                T_map_sensor=T,
                features=FeaturesIn(f["global_descriptor"], f["keypoints"], f["local_features"]),
                key=None if key_prefix is None else f"{key_prefix}{i}",
                metadata=dict(metadata or {}),
            )
        )
    return out


PRECOMPUTED = {"kind": "precomputed", "name": "egonn", "global_dim": 16, "local_dim": 8}


@dataclass
class BalmMap:
    """The ``balm`` map: the fixture's database scans, inserted in one request."""

    name: str
    ids: dict[int, int]  # fixture file index -> keyframe id
    version: int
    queries: list[int]  # fixture file indices of the revisit queries
    seq: KittiSequence

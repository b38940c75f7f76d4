"""What an encoder produces for one scan, and how encoders are identified."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .errors import EncoderMismatchError, InputError


@dataclass(frozen=True)
class EncoderIdentity:
    """Names an encoder and every parameter that changes its output.

    Two feature sets are comparable only if their identities are equal. ``fingerprint``
    is a short stable hash of the whole identity, recorded with every map.
    """

    name: str
    version: str = "1"
    params: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "params": self.params}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EncoderIdentity:
        return cls(name=d["name"], version=str(d.get("version", "1")), params=d.get("params", {}))

    @property
    def fingerprint(self) -> str:
        blob = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"), default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, EncoderIdentity) and self.fingerprint == other.fingerprint

    def __hash__(self) -> int:
        return hash(self.fingerprint)

    def require_same(self, other: EncoderIdentity, what: str = "features") -> None:
        """Raise :class:`EncoderMismatchError` unless ``other`` is this encoder."""
        if other != self:
            raise EncoderMismatchError(
                f"{what} come from encoder {other.name!r} (fingerprint {other.fingerprint}), "
                f"but this map uses {self.name!r} (fingerprint {self.fingerprint})"
            )


@dataclass(frozen=True)
class Features:
    """Everything the localizer needs from one scan.

    - ``global_descriptor``: ``[G]`` float32, L2-normalised (retrieval by inner product);
    - ``keypoints``: ``[N, 3]`` float32, metres, in the scan's sensor frame;
    - ``local_features``: ``[N, D]`` float32, one row per keypoint;
    - ``encoder``: the identity of the encoder that produced them;
    - ``global_variants``: ``[V, G]`` float32 or None, a query's global descriptor
      computed about other centres than the sensor (:meth:`Encoder.encode_query`), each
      row normalised as ``global_descriptor``; retrieval only, never stored with a
      keyframe.
    """

    global_descriptor: np.ndarray
    keypoints: np.ndarray
    local_features: np.ndarray
    encoder: EncoderIdentity
    global_variants: np.ndarray | None = None

    @classmethod
    def validated(
        cls,
        global_descriptor: Any,
        keypoints: Any,
        local_features: Any,
        encoder: EncoderIdentity,
        *,
        global_dim: int | None = None,
        local_dim: int | None = None,
    ) -> Features:
        """Check shapes, dtypes and finiteness, cast to float32 and normalise the descriptor.

        Raises :class:`InputError` naming the offending field.
        """
        g = _as_float_array("global_descriptor", global_descriptor, ndim=1)
        k = _as_float_array("keypoints", keypoints, ndim=2)
        f = _as_float_array("local_features", local_features, ndim=2)
        if g.shape[0] == 0:
            raise InputError("global_descriptor is empty")
        if global_dim is not None and g.shape[0] != global_dim:
            raise InputError(f"global_descriptor has length {g.shape[0]}, expected {global_dim}")
        if k.shape[1] != 3:
            raise InputError(f"keypoints must have shape [N, 3], got {list(k.shape)}")
        if f.shape[0] != k.shape[0]:
            raise InputError(
                f"local_features has {f.shape[0]} rows but keypoints has {k.shape[0]}; "
                "one feature row per keypoint is required"
            )
        if local_dim is not None and k.shape[0] > 0 and f.shape[1] != local_dim:
            raise InputError(f"local_features has dimension {f.shape[1]}, expected {local_dim}")
        if k.shape[0] == 0 and local_dim is not None:
            f = np.zeros((0, local_dim), dtype=np.float32)  # no rows: the encoder's width
        if k.shape[0] > 1 and _repeats_a_position(k):
            # a keypoint repeated with its feature (padding to a fixed count, say) adds no
            # evidence but would match itself as a perfectly consistent cluster in SGV
            rows = np.concatenate([k, f], axis=1)
            _, first = np.unique(rows, axis=0, return_index=True)
            if len(first) < len(rows):
                keep = np.sort(first)
                k, f = k[keep], f[keep]
        g64 = g.astype(np.float64)  # float32 squares overflow from ~1e19 and vanish below 1e-19
        norm = float(np.linalg.norm(g64))
        if norm == 0.0:
            raise InputError("global_descriptor is all zeros and cannot be normalised")
        return cls((g64 / norm).astype(np.float32), k, f, encoder)

    def with_variants(self, start: int, blocks: np.ndarray | None) -> Features:
        """These features with ``global_variants``: the global descriptor once per row of
        ``blocks`` ``[V, B]``, its block ``[start, start + B)`` replaced by that row scaled
        to the block's length in the descriptor (every other value left as it is; a row
        of zeros, a centre that sees nothing, leaves the block as it is); none or an
        empty array: None."""
        if blocks is None or len(blocks) == 0:
            return replace(self, global_variants=None)
        b = np.asarray(blocks, dtype=np.float64).reshape(len(blocks), -1)
        end = start + b.shape[1]
        g = self.global_descriptor
        norm = np.linalg.norm(b, axis=1, keepdims=True)
        rows = np.repeat(g[None], len(b), axis=0)
        length = float(np.linalg.norm(g[start:end].astype(np.float64)))
        seen = norm[:, 0] > 0  # a centre that sees nothing keeps the sensor's block
        rows[seen, start:end] = b[seen] / norm[seen] * length
        return replace(self, global_variants=rows.astype(np.float32))

    @property
    def num_keypoints(self) -> int:
        return int(self.keypoints.shape[0])


def _repeats_a_position(keypoints: np.ndarray) -> bool:
    """Whether two rows of ``keypoints`` ``[N, 3]`` are equal: a sort of the positions,
    about 20 times cheaper than looking for repeated rows of positions and features,
    which only a repeated position can hold."""
    ks = keypoints[np.lexsort(keypoints.T[::-1])]
    return bool((ks[1:] == ks[:-1]).all(axis=1).any())


def _as_float_array(name: str, value: Any, ndim: int) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} is not a numeric array: {exc}") from None
    if arr.dtype.kind not in "fiu":
        raise InputError(f"{name} must be numeric, got dtype {arr.dtype}")
    if arr.ndim != ndim:
        raise InputError(f"{name} must have {ndim} dimension(s), got shape {list(arr.shape)}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.isfinite(arr).all():
        bad = int((~np.isfinite(arr)).sum())
        raise InputError(f"{name} contains {bad} non-finite value(s) (NaN or inf)")
    return arr

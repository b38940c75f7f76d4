"""Schemathesis hooks for a command-line run against a live service (docs/OPERATIONS.md,
"Fuzzing"): MessagePack request bodies, as tests/service/test_fuzz.py sends them.

    SCHEMATHESIS_HOOKS=schemathesis_hooks PYTHONPATH=tests/service schemathesis run ...
"""

from __future__ import annotations

import msgpack
import schemathesis


def _packable(value):  # noqa: ANN001, ANN202
    """MessagePack has 64-bit integers only: larger ones travel as floats."""
    if isinstance(value, dict):
        return {k: _packable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_packable(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool) and not -(2**63) <= value < 2**64:
        return float(value)
    return value


@schemathesis.serializer("application/msgpack")
def _msgpack(ctx, value):  # noqa: ANN001, ANN202 - schemathesis' hook signature
    return msgpack.packb(_packable(value), use_bin_type=True)


@schemathesis.serializer("application/x-tar")
def _tar(ctx, value):  # noqa: ANN001, ANN202 - schemathesis' hook signature
    """Map archives are binary: generated strings go as their bytes (the service must
    refuse them as not an archive, never fail)."""
    return value if isinstance(value, bytes) else str(value).encode()

"""Exceptions raised by the engine.

All derive from :class:`SgvlocError`. The HTTP layer maps them to status codes:

- :class:`InputError` (bad data from the caller: wrong shape, NaN, empty scan, malformed
  file) -> 422 / 400; :class:`EmptyScanError`, a valid scan in which the map's encoder
  finds nothing to describe, -> 422 ``empty_scan``;
- :class:`EncoderMismatchError` (features from another encoder than the map's) -> 409;
- :class:`NotFoundError` (unknown keyframe or map) -> 404;
- :class:`ConflictError` (duplicate name or key) -> 409;
- :class:`DeadlineExceeded` (a call ran past its time limit and stopped) -> 503;
- :class:`StorageFullError` (the disk is full; nothing was stored) -> 507.
"""


class SgvlocError(Exception):
    """Base class of every error raised by sgvloc."""


class InputError(SgvlocError, ValueError):
    """The caller's data is malformed; the message names the field and the problem."""


class EmptyScanError(InputError):
    """The encoder found nothing to describe in a scan (too sparse for it, or nothing
    but ground): a well-formed scan that this encoder cannot use."""


class ScanFormatError(InputError):
    """A scan file cannot be read; the message names the file and the problem."""


class EncoderMismatchError(SgvlocError):
    """Features were produced by an encoder other than the one a map was built with."""


class NotFoundError(SgvlocError, KeyError):
    """An id or name does not exist."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class ConflictError(SgvlocError):
    """The operation conflicts with existing state (duplicate name, key, ...)."""


class DeadlineExceeded(SgvlocError):
    """The call ran past its time limit (:mod:`sgvloc.core.deadline`) and stopped."""


class CallerGone(DeadlineExceeded):
    """The caller went away (the service's client closed its connection), so the call
    stopped at its next step: nobody would read its answer."""


class StorageFullError(SgvlocError):
    """A write found no space left; it was rolled back and nothing was stored."""

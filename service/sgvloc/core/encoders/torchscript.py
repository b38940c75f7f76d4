"""Learned encoder plug-in: a TorchScript model file named in the map's settings.

Model contract:

- input: one float32 tensor ``[P, 4]`` (x, y, z, intensity) on the model's device. The
  encoder runs its preprocessing first (:func:`sgvloc.core.preprocess.preprocess`, which
  keeps xyz only), so the intensity column is always **zero**; a model that needs
  intensity is not supported by this plug-in;
- output: a tuple ``(global [G], keypoints [N, 3], local [N, D])`` of float tensors,
  keypoints in metres in the scan's frame.

``G`` and ``D`` come from integer attributes ``global_dim`` / ``local_dim`` on the model
when it has them, otherwise from one forward pass on a fixed synthetic cloud at load
time. The identity holds the model file's SHA-256 and the preprocessing settings, so
features from two different model files never mix. The model runs under
``torch.inference_mode()``.
"""

from __future__ import annotations

import hashlib
import logging
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from ..config import PreprocessConfig
from ..errors import InputError
from ..features import EncoderIdentity, Features
from ..preprocess import ground_fit
from .base import Encoder

log = logging.getLogger(__name__)


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _probe_cloud() -> np.ndarray:
    """A fixed synthetic cloud ``[2048, 3]`` used to discover the output dimensions."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-20.0, 20.0, size=(2048, 2))
    z = rng.uniform(-1.5, 3.0, size=(2048, 1))
    return np.hstack([xy, z]).astype(np.float32)


class TorchScriptEncoder(Encoder):
    """Runs a TorchScript model on the preprocessed scan."""

    NAME = "torchscript"
    VERSION = "1"

    def __init__(
        self,
        model_path: str | Path,
        preprocess_config: PreprocessConfig | None = None,
        device: str = "cpu",
    ) -> None:
        """Load the model. ``device``: ``"cpu"``, ``"cuda"`` or ``"auto"`` (CUDA if any).

        Raises :class:`InputError` naming the path if the file is missing or is not a
        loadable TorchScript model, or if the model's outputs break the contract.
        """
        import torch

        self.model_path = Path(model_path)
        self.preprocess_config = preprocess_config or PreprocessConfig()
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        if device == "cuda" and not torch.cuda.is_available():
            raise InputError("torchscript encoder: device 'cuda' requested but CUDA is absent")
        self.device = torch.device(device)
        if not self.model_path.is_file():
            raise InputError(f"TorchScript model file not found: {str(self.model_path)!r}")
        try:
            self.sha256 = file_sha256(self.model_path)
            with warnings.catch_warnings():  # deprecated upstream, still the format
                warnings.simplefilter("ignore", DeprecationWarning)
                self.model = torch.jit.load(str(self.model_path), map_location=self.device)
        except (RuntimeError, ValueError, OSError) as exc:
            raise InputError(
                f"cannot load TorchScript model {str(self.model_path)!r}: {exc}"
            ) from None
        self.model.eval()

        dims = self._declared_dims()
        if dims is None:
            g, _, f = self._run(_probe_cloud())
            dims = (g.shape[0], f.shape[1])
        self.global_dim, self.local_dim = dims
        self.identity = EncoderIdentity(
            name=self.NAME,
            version=self.VERSION,
            params={
                "model_sha256": self.sha256,
                "preprocess": self.preprocess_config.model_dump(),
                **ground_fit(self.preprocess_config),
                "global_dim": self.global_dim,
                "local_dim": self.local_dim,
            },
        )
        log.info(
            "loaded TorchScript encoder %s (sha256 %s..., G=%d, D=%d, %s)",
            self.model_path,
            self.sha256[:12],
            self.global_dim,
            self.local_dim,
            self.device,
        )

    def _declared_dims(self) -> tuple[int, int] | None:
        g = getattr(self.model, "global_dim", None)
        d = getattr(self.model, "local_dim", None)
        if isinstance(g, int) and isinstance(d, int) and g > 0 and d > 0:
            return g, d
        return None

    def _run(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forward ``xyz [M, 3]`` (zero intensity appended) and check the output shapes."""
        import torch

        inp = np.zeros((len(xyz), 4), dtype=np.float32)  # [M, 4] x y z intensity=0
        inp[:, :3] = xyz
        try:
            with torch.inference_mode():
                out: Any = self.model(torch.from_numpy(inp).to(self.device))
        except RuntimeError as exc:
            raise InputError(f"TorchScript model {str(self.model_path)!r} failed: {exc}") from None
        return self._check_output(out)

    def _check_output(self, out: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        import torch

        where = f"TorchScript model {str(self.model_path)!r}"
        if not isinstance(out, (tuple, list)) or len(out) != 3:
            kind = f"a {type(out).__name__}"
            if isinstance(out, (tuple, list)):
                kind += f" of length {len(out)}"
            raise InputError(
                f"{where} returned {kind}; expected a tuple (global, keypoints, local)"
            )
        names = ("global", "keypoints", "local")
        for name, t in zip(names, out, strict=True):
            if not isinstance(t, torch.Tensor):
                raise InputError(f"{where}: output {name} is a {type(t).__name__}, not a tensor")
        g, k, f = (t.detach().to("cpu", torch.float32).numpy() for t in out)
        shapes = f"global {list(g.shape)}, keypoints {list(k.shape)}, local {list(f.shape)}"
        if g.ndim != 1 or k.ndim != 2 or k.shape[1] != 3 or f.ndim != 2 or len(f) != len(k):
            raise InputError(
                f"{where} returned {shapes}; expected global [G], keypoints [N, 3], "
                "local [N, D] with the same N"
            )
        return g, k, f

    def encode_cloud(self, cloud: np.ndarray) -> Features:
        """Run the model on a preprocessed cloud ``[M, 3]`` and validate its outputs.

        Raises :class:`InputError` on outputs that do not match the model's dimensions.
        """
        g, k, f = self._run(cloud)
        if g.shape[0] != self.global_dim or (len(k) > 0 and f.shape[1] != self.local_dim):
            raise InputError(
                f"TorchScript model {str(self.model_path)!r} returned global "
                f"{list(g.shape)}, local {list(f.shape)}; expected global [{self.global_dim}] "
                f"and local [N, {self.local_dim}]"
            )
        return Features.validated(
            g, k, f, self.identity, global_dim=self.global_dim, local_dim=self.local_dim
        )

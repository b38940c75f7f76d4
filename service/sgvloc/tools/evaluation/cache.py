"""On-disk feature cache for evaluation runs.

One ``.npz`` per (encoder, scan file) under ``ROOT/<encoder fingerprint>/``, named by a
hash of the scan's absolute path, size and modification time, so a changed scan or
another encoder setting never reuses stale features. Each file holds the global
descriptor, keypoints, local features and the preprocessed cloud (for ICP refinement).

The learned encoder with FPFH keypoints (``local_features = "fpfh"``) takes the cloud,
keypoints and FPFH of a scan from the handcrafted encoder's files when they are there
(the same preprocessing and features: the encoder self-test runs both), and computes only
the network's part.

With ``fov_deg`` every scan (and image) is first cropped to that horizontal field of view
about the sensor's forward axis (a forward-looking sensor emulated on 360-degree data);
those features live in ``<fingerprint>-fov<deg>/``.

A ``.png`` file is a kitti-bev BEV image (:func:`sgvloc.core.bev.load_bev_image`): it is
described by the encoder's ``encode_image`` and has no cloud (an empty ``[0, 3]`` one is
stored).
Clouds are read only when asked for: ``np.load`` of an ``.npz`` reads members lazily.
Writes go to a temporary file moved into place with ``os.replace``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np

from sgvloc.core.encoders import Encoder
from sgvloc.core.errors import InputError
from sgvloc.core.features import Features
from sgvloc.core.files import write_whole

log = logging.getLogger(__name__)


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/sgvloc/features`` (``~/.cache/sgvloc/features`` by default)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(Path.home(), ".cache")
    return Path(base) / "sgvloc" / "features"


class FeatureCache:
    """Features of scan files for one encoder, cached on disk.

    ``hits`` and ``misses`` count :meth:`get` calls served from disk and computed.
    """

    def __init__(
        self, root: str | os.PathLike, encoder: Encoder, fov_deg: float | None = None
    ) -> None:
        self.encoder = encoder
        #: scans and images cropped to this horizontal field of view before encoding
        self.fov_deg = fov_deg if fov_deg is not None and fov_deg < 360.0 else None
        fov = f"-fov{self.fov_deg:g}" if self.fov_deg else ""
        self.dir = Path(root) / (encoder.identity.fingerprint + fov)
        self.dir.mkdir(parents=True, exist_ok=True)
        ident = self.dir / "encoder.json"
        if not ident.exists():
            ident.write_text(json.dumps(encoder.identity.to_dict(), indent=1, default=str))
        self.hits = 0
        self.misses = 0
        #: the cache of the encoder that makes this one's local part (the learned encoder
        #: with FPFH keypoints: the handcrafted encoder's), whose files are reused
        local = getattr(encoder, "fpfh", None)
        self.local_from = FeatureCache(root, local, fov_deg) if local is not None else None

    def path_for(self, scan_path: str | os.PathLike) -> Path:
        """The cache file of a scan file (depends on its path, size and mtime)."""
        p = Path(scan_path).resolve()
        st = p.stat()
        key = f"{p}|{st.st_size}|{st.st_mtime_ns}"
        return self.dir / (hashlib.sha256(key.encode()).hexdigest()[:24] + ".npz")

    def get(self, scan_path: str | os.PathLike, centres: np.ndarray | None = None) -> Features:
        """Features of a scan file: from the cache, or computed (and stored). With
        ``centres`` ``[C, 2]`` as a query's (:meth:`Encoder.encode_query`): a file
        stored without these centres' variants is computed again."""
        f = self.path_for(scan_path)
        want = None if centres is None else np.asarray(centres, dtype=np.float64).reshape(-1, 2)
        if f.exists():
            try:
                with np.load(f) as z:
                    variants = None
                    if want is not None:
                        if "centres" not in z.files or not np.array_equal(z["centres"], want):
                            raise LookupError
                        variants = z["global_variants"]
                        if len(variants) != (len(want) if self.encoder.describes_displaced else 0):
                            raise LookupError  # stored before the encoder described them
                    feats = Features(
                        z["global_descriptor"],
                        z["keypoints"],
                        z["local_features"],
                        self.encoder.identity,
                        variants if variants is not None and len(variants) else None,
                    )
                self.hits += 1
                return feats
            except LookupError:  # stored without these centres' variants
                pass
            except (OSError, KeyError, ValueError) as exc:  # damaged file: recompute
                log.warning("feature cache file %s unreadable (%s); recomputing", f, exc)
        self.misses += 1
        feats, cloud = self._compute(Path(scan_path), want)
        self._write(f, feats, cloud, want)
        return feats

    def _compute(self, path: Path, centres: np.ndarray | None) -> tuple[Features, np.ndarray]:
        if path.suffix.lower() == ".png":
            from sgvloc.core.bev import load_bev_image

            encode_image = getattr(self.encoder, "encode_image", None)
            if encode_image is None:
                raise InputError(
                    f"encoder {self.encoder.identity.name!r} cannot encode BEV images "
                    f"({path.name}); use an encoder with encode_image, e.g. kind 'bev'"
                )
            image = load_bev_image(path)
            if self.fov_deg:
                from sgvloc.core.bev import crop_image_azimuth

                image = crop_image_azimuth(image, self.fov_deg)
            if centres is not None and self.encoder.describes_displaced:
                return encode_image(image, centres=centres), np.zeros((0, 3), np.float32)
            return encode_image(image), np.zeros((0, 3), np.float32)
        if self.local_from is not None:  # that encoder's cloud and FPFH, if cached
            donor, parts = self.local_from.path_for(path), None
            try:
                with np.load(donor) as z:
                    parts = z["keypoints"], z["local_features"], z["cloud"]
            except FileNotFoundError:
                pass
            except (OSError, KeyError, ValueError) as exc:  # damaged file: compute
                log.warning("feature cache file %s unreadable (%s); recomputing", donor, exc)
            if parts is not None:
                kp, local, cloud = parts
                return self.encoder.encode_query(cloud, centres, local=(kp, local)), cloud
        from sgvloc.core.io import read_scan
        from sgvloc.core.preprocess import crop_azimuth

        points = read_scan(path).points
        if self.fov_deg:
            points = crop_azimuth(points, self.fov_deg)
        cloud = self.encoder.prepare(points)  # [M, 3]
        return self.encoder.encode_query(cloud, centres), cloud

    def cloud(self, scan_path: str | os.PathLike) -> np.ndarray:
        """The preprocessed cloud ``[M, 3]`` of a scan (computed if not cached)."""
        f = self.path_for(scan_path)
        if not f.exists():
            self.get(scan_path)
        with np.load(f) as z:
            return np.asarray(z["cloud"], dtype=np.float32)

    def _write(
        self, f: Path, feats: Features, cloud: np.ndarray, centres: np.ndarray | None
    ) -> None:
        extra = {}
        if centres is not None:  # the centres asked for, and what they gave (maybe none)
            g = feats.global_variants
            extra = {
                "centres": centres,
                "global_variants": np.zeros((0, len(feats.global_descriptor)), np.float32)
                if g is None
                else g,
            }

        def write(part: Path) -> None:
            with open(part, "xb") as fh:
                np.savez(
                    fh,
                    global_descriptor=feats.global_descriptor,
                    keypoints=feats.keypoints,
                    local_features=feats.local_features,
                    cloud=np.asarray(cloud, dtype=np.float32),
                    **extra,
                )

        write_whole(f, write)

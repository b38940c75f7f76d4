"""Retrieval: a FAISS index of global descriptors with stable int64 ids.

Inner product on L2-normalised descriptors (= cosine similarity). Three index kinds:

- ``flat`` (default): exact search, ``IndexIDMap2(IndexFlatIP)``; removal by id.
- ``ivf``: ``IndexIVFFlat``, trained lazily. Until the map holds ``train_size`` vectors
  the index is exact (flat); when it crosses that size the vectors are moved into a
  freshly trained IVF index. ``nprobe`` is fixed at construction: it is index state and
  must not be varied per request while other threads search.
- ``hnsw``: ``IndexHNSWFlat``. HNSW cannot remove vectors, so removed ids are hidden
  (tombstones, filtered from results) and the graph is rebuilt without them once they
  exceed a quarter of the index or when it is saved.

Concurrency: searches run concurrently, modifications are exclusive (a readers-writer
lock inside the wrapper). Snapshots are written to a temporary file and moved into
place with ``os.replace`` so a crash never leaves a half-written index.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import faiss
import numpy as np

from ._rwlock import RWLock
from .config import RetrievalConfig
from .errors import ConflictError, InputError, NotFoundError
from .files import write_text_whole, write_whole

log = logging.getLogger(__name__)

#: IVF and HNSW searches among selected ids compare this many stored vectors at a time
#: (about 14 MB at 876 dimensions), whatever the size of the selection
AMONG_CHUNK = 4096
#: a selection of every keyframe is searched as the whole map for this many more hits,
#: so that keyframes added meanwhile (not selected) can be dropped
AMONG_SLACK = 16


def _holds(sorted_ids: np.ndarray, id_: int) -> bool:
    """Whether ``id_`` is in the sorted array ``sorted_ids``."""
    i = int(np.searchsorted(sorted_ids, id_))
    return i < len(sorted_ids) and int(sorted_ids[i]) == id_


@dataclass(frozen=True)
class SearchHit:
    """One retrieved keyframe: its id and inner-product similarity (higher is closer)."""

    id: int
    similarity: float


class FaissIndex:
    """A FAISS index of L2-normalised descriptors addressed by stable int64 ids."""

    def __init__(self, dim: int, config: RetrievalConfig | None = None) -> None:
        if dim <= 0:
            raise InputError(f"descriptor dimension must be positive, got {dim}")
        self.dim = int(dim)
        self.config = config or RetrievalConfig()
        self._lock = RWLock()
        self._tombstones: set[int] = set()
        self._index = self._new_index(trained_ivf=False)

    # -- construction -------------------------------------------------------------------

    @property
    def train_size(self) -> int:
        """IVF: vectors needed before the index is trained (FAISS wants ~39 per cell)."""
        return 39 * self.config.nlist

    @property
    def kind(self) -> str:
        """The index kind in use now ('ivf' reports 'flat' until it has been trained)."""
        inner = faiss.downcast_index(self._index.index) if self._is_idmap() else self._index
        if isinstance(inner, faiss.IndexHNSW):
            return "hnsw"
        if isinstance(inner, faiss.IndexIVF):
            return "ivf"
        return "flat"

    def _is_idmap(self) -> bool:
        return isinstance(self._index, faiss.IndexIDMap2)

    def _new_index(self, trained_ivf: bool) -> faiss.Index:
        cfg = self.config
        if cfg.index == "hnsw":
            hnsw = faiss.IndexHNSWFlat(self.dim, cfg.hnsw_m, faiss.METRIC_INNER_PRODUCT)
            hnsw.hnsw.efSearch = cfg.ef_search
            return faiss.IndexIDMap2(hnsw)
        if cfg.index == "ivf" and trained_ivf:
            quantizer = faiss.IndexFlatIP(self.dim)
            ivf = faiss.IndexIVFFlat(quantizer, self.dim, cfg.nlist, faiss.METRIC_INNER_PRODUCT)
            ivf.nprobe = cfg.nprobe
            return ivf
        return faiss.IndexIDMap2(faiss.IndexFlatIP(self.dim))

    # -- inspection ---------------------------------------------------------------------

    def __len__(self) -> int:
        return int(self._index.ntotal) - len(self._tombstones)

    def ids(self) -> np.ndarray:
        """All live ids, sorted ``[M]`` int64."""
        with self._lock.read():
            return np.sort(self._live_ids())

    def memory_bytes(self) -> int:
        """Bytes of the stored vectors and ids (graph links of HNSW included, roughly)."""
        n = int(self._index.ntotal)
        links = 2 * self.config.hnsw_m * 4 if self.kind == "hnsw" else 0
        return n * (self.dim * 4 + 8 + links)

    def _all_ids(self) -> np.ndarray:
        if self._is_idmap():
            return faiss.vector_to_array(self._index.id_map).astype(np.int64)
        invlists = self._index.invlists
        out = [
            faiss.rev_swig_ptr(invlists.get_ids(i), invlists.list_size(i)).copy()
            for i in range(invlists.nlist)
            if invlists.list_size(i)
        ]
        return np.concatenate(out).astype(np.int64) if out else np.zeros(0, np.int64)

    def _live_ids(self) -> np.ndarray:
        ids = self._all_ids()
        if self._tombstones:
            ids = ids[~np.isin(ids, np.fromiter(self._tombstones, np.int64))]
        return ids

    def retired(self, id_: int) -> bool:
        """Whether ``id_`` was removed but is still held (HNSW, until it compacts)."""
        return int(id_) in self._tombstones

    def __contains__(self, id_: int) -> bool:
        with self._lock.read():
            return int(id_) in set(self._live_ids().tolist())

    def reconstruct(self, ids: np.ndarray) -> np.ndarray:
        """The stored vectors of ``ids`` ``[M, dim]``."""
        with self._lock.read():
            return self._reconstruct(np.asarray(ids, dtype=np.int64))

    def _reconstruct(self, ids: np.ndarray) -> np.ndarray:
        out = np.empty((len(ids), self.dim), dtype=np.float32)
        for row, i in enumerate(ids.tolist()):
            out[row] = self._index.reconstruct(int(i))
        return out

    # -- modification -------------------------------------------------------------------

    def _prepare(self, vectors: np.ndarray) -> np.ndarray:
        x = np.asarray(vectors)
        if x.ndim == 1:
            x = x[None, :]
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise InputError(f"descriptors must have shape [M, {self.dim}], got {list(x.shape)}")
        x = np.ascontiguousarray(x, dtype=np.float32).copy()
        if not np.isfinite(x).all():
            raise InputError("descriptors contain NaN or inf")
        norms = np.linalg.norm(x, axis=1)
        if (norms == 0).any():
            raise InputError("a descriptor is all zeros and cannot be normalised")
        faiss.normalize_L2(x)
        return x

    def add(self, ids: np.ndarray, vectors: np.ndarray) -> None:
        """Add vectors under the given ids; an id already present raises ConflictError."""
        ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
        x = self._prepare(vectors)
        if len(ids) != len(x):
            raise InputError(f"{len(ids)} ids for {len(x)} descriptors")
        if len(np.unique(ids)) != len(ids):
            raise ConflictError("duplicate ids in one add() call")
        with self._lock.write():
            if self._tombstones and not self._tombstones.isdisjoint(ids.tolist()):
                self._compact()  # removed ids coming back: drop the tombstones first
            present = np.isin(ids, self._all_ids())
            if present.any():
                raise ConflictError(f"id(s) already in the index: {ids[present][:5].tolist()}")
            self._index.add_with_ids(x, ids)
            self._maybe_train_ivf()

    def remove(self, ids: np.ndarray) -> int:
        """Remove ids; unknown ids raise NotFoundError (nothing is removed then)."""
        ids = np.atleast_1d(np.asarray(ids, dtype=np.int64))
        with self._lock.write():
            live = self._live_ids()
            missing = ids[~np.isin(ids, live)]
            if len(missing):
                raise NotFoundError(f"id(s) not in the index: {missing[:5].tolist()}")
            if self.kind == "hnsw":
                self._tombstones.update(ids.tolist())
                if len(self._tombstones) > max(16, self._index.ntotal // 4):
                    self._compact()
            else:
                self._index.remove_ids(faiss.IDSelectorArray(ids))
            return len(ids)

    def _compact(self) -> None:
        """Rebuild from the live vectors (drops HNSW tombstones)."""
        live = self._live_ids()
        vectors = self._reconstruct(live)
        self._index = self._new_index(trained_ivf=self.kind == "ivf")
        if self.kind == "ivf":
            self._index.train(vectors)
            self._index.set_direct_map_type(faiss.DirectMap.Hashtable)
        self._tombstones.clear()
        if len(live):
            self._index.add_with_ids(vectors, live)

    def _maybe_train_ivf(self) -> None:
        if self.config.index != "ivf" or self.kind == "ivf" or self._index.ntotal < self.train_size:
            return
        ids = self._all_ids()
        vectors = self._reconstruct(ids)
        ivf = self._new_index(trained_ivf=True)
        ivf.train(vectors)
        ivf.set_direct_map_type(faiss.DirectMap.Hashtable)
        ivf.add_with_ids(vectors, ids)
        self._index = ivf
        log.info("trained IVF index (nlist=%d) on %d descriptors", self.config.nlist, len(ids))

    # -- search -------------------------------------------------------------------------

    def search(
        self, queries: np.ndarray, k: int, among: np.ndarray | None = None
    ) -> list[list[SearchHit]]:
        """Top-k by inner product for each query row; fewer hits if the index is smaller.

        ``among``: search only these ids (a prior region's keyframes), exactly: the flat
        index filters with a FAISS ID selector; IVF and HNSW, whose approximate search
        can miss members of a small selection, compare the query with the selected
        vectors directly, :data:`AMONG_CHUNK` of them at a time (bounded memory). A
        selection that holds every keyframe is the plain search.
        """
        if k <= 0:
            raise InputError(f"k must be positive, got {k}")
        q = self._prepare(queries)
        if among is not None:
            among = np.asarray(among, dtype=np.int64).ravel()
            if len(among) > 1 and not (among[1:] > among[:-1]).all():
                among = np.unique(among)  # sorted, once each (a prior's ids already are)
            hits = self._search_among(q, k, among)
            if hits is not None:
                return hits
            # every keyframe is selected; one added since is not, so it is filtered out
            picked = self._search_all(q, k + AMONG_SLACK)
            return [[h for h in row if _holds(among, h.id)][:k] for row in picked]
        return self._search_all(q, k)

    def _search_all(self, q: np.ndarray, k: int) -> list[list[SearchHit]]:
        with self._lock.read():
            if self._index.ntotal == 0:
                return [[] for _ in range(len(q))]
            fetch = min(k + len(self._tombstones), int(self._index.ntotal))
            sims, ids = self._index.search(q, fetch)
            dead = self._tombstones
        results = []
        for row_sims, row_ids in zip(sims, ids, strict=True):
            hits = [
                SearchHit(int(i), float(s))
                for s, i in zip(row_sims, row_ids, strict=True)
                if i >= 0 and int(i) not in dead
            ]
            results.append(hits[:k])
        return results

    def search_blocks(
        self,
        query: np.ndarray,
        k: int,
        blocks: tuple[int, ...],
        among: np.ndarray | None = None,
        variants: np.ndarray | None = None,
    ) -> list[list[SearchHit]]:
        """One query's top-k by each block of its descriptor on its own (the other
        blocks zeroed; stored vectors are normalised per block, so this ranks by that
        block's cosine similarity). ``blocks`` are the block lengths (summing to ``dim``).

        ``variants`` ``[V, dim]``: the same query's descriptor computed otherwise (about
        displaced centres, ``Features.global_variants``); a block whose variants differ
        from the query's ranks each keyframe by its best similarity over them all (the
        top-k of that maximum: the union of each row's top-k holds it exactly). Every
        hit's similarity is the whole query descriptor's (:meth:`search`'s)."""
        q = np.asarray(query, dtype=np.float32).reshape(-1)
        if sum(blocks) != self.dim or len(q) != self.dim or min(blocks, default=0) < 1:
            raise InputError(
                f"descriptor blocks {list(blocks)} do not cover a {self.dim}-D index "
                f"(query has {len(q)})"
            )
        whole = self._prepare(q)[0]
        alt = np.zeros((0, self.dim), np.float32)
        if variants is not None:
            alt = np.asarray(variants, dtype=np.float32).reshape(-1, self.dim)
        ends = np.cumsum(blocks)
        rows: list[np.ndarray] = []  # masked query rows, each serving one block
        owner: list[int] = []
        for b, (start, end) in enumerate(zip(ends - blocks, ends, strict=True)):
            seen: list[np.ndarray] = []
            for v in (q, *alt):
                part = v[start:end]
                if not part.any() or any(np.array_equal(part, p) for p in seen):
                    continue  # an empty block finds nothing; an unchanged one adds nothing
                seen.append(part)
                row = np.zeros(self.dim, dtype=np.float32)
                row[start:end] = part
                rows.append(row)
                owner.append(b)
        found = self.search(np.stack(rows), k, among=among) if rows else []  # one call
        lists: list[list[SearchHit]] = [[] for _ in blocks]
        for b in range(len(blocks)):
            mine = [hits for o, hits in zip(owner, found, strict=True) if o == b]
            if len(mine) == 1:
                lists[b] = mine[0]
            elif mine:
                best: dict[int, float] = {}
                for hits in mine:
                    for h in hits:
                        best[h.id] = max(h.similarity, best.get(h.id, -np.inf))
                ranked = sorted(best.items(), key=lambda kv: (-kv[1], kv[0]))[:k]
                lists[b] = [SearchHit(i, s) for i, s in ranked]
        sims: dict[int, float] = {}
        with self._lock.read():
            for i in {h.id for hits in lists for h in hits}:
                if i in self._tombstones:
                    continue
                try:
                    sims[i] = float(self._index.reconstruct(i) @ whole)
                except RuntimeError:  # removed since the search
                    continue
        return [[SearchHit(h.id, sims[h.id]) for h in hits if h.id in sims] for hits in lists]

    def _search_among(
        self, q: np.ndarray, k: int, among: np.ndarray
    ) -> list[list[SearchHit]] | None:
        """The search among sorted unique ids ``among``; None when they hold every live
        keyframe (the caller searches them all instead)."""
        with self._lock.read():
            live = self._live_ids()
            among = among[np.isin(among, live)]  # unknown ids select nothing
            if len(among) == 0 or self._index.ntotal == 0:
                return [[] for _ in range(len(q))]
            if len(among) == len(live):
                return None
            if self.kind == "flat":
                sel = faiss.IDSelectorBatch(among)
                sims, ids = self._index.search(
                    q, min(k, len(among)), params=faiss.SearchParameters(sel=sel)
                )
            else:
                sims, ids = self._exact_among(q, k, among)
        return [
            [SearchHit(int(i), float(v)) for v, i in zip(rs, ri, strict=True) if i >= 0]
            for rs, ri in zip(sims, ids, strict=True)
        ]

    def _exact_among(
        self, q: np.ndarray, k: int, among: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Top-k of ``q`` ``[Q, dim]`` among ``among`` by comparing with their stored
        vectors, :data:`AMONG_CHUNK` at a time: ``(sims, ids)`` ``[Q, <=k]``. Call under
        the read lock."""
        sims = np.full((len(q), 0), -np.inf, dtype=np.float32)
        ids = np.zeros((len(q), 0), dtype=np.int64)
        for start in range(0, len(among), AMONG_CHUNK):
            part = among[start : start + AMONG_CHUNK]
            s = q @ self._index.reconstruct_batch(part).T  # [Q, chunk]
            sims = np.concatenate([sims, s], axis=1)
            ids = np.concatenate([ids, np.broadcast_to(part, s.shape)], axis=1)
            order = np.argsort(-sims, axis=1, kind="stable")[:, :k]  # earlier ids first
            sims, ids = (
                np.take_along_axis(sims, order, axis=1),
                np.take_along_axis(ids, order, axis=1),
            )
        return sims, ids

    # -- persistence --------------------------------------------------------------------

    def save(self, path: str | Path) -> None:
        """Atomic snapshot: written to a temporary file in ``path``'s folder (which must
        exist), flushed to disk, then moved into place. A failed write (a full disk)
        raises OSError and leaves the previous snapshot as it was."""
        path = Path(path)
        if self._tombstones:
            with self._lock.write():
                self._compact()
        with self._lock.read():  # searches go on; the disk is written outside the lock
            data = faiss.serialize_index(self._index)  # FAISS's own writer reports no errors

        def write(part: Path) -> None:
            with open(part, "xb") as f:
                f.write(memoryview(data))
                f.flush()
                os.fsync(f.fileno())

        write_whole(path, write)
        meta = {"dim": self.dim, "config": self.config.model_dump()}
        write_text_whole(path.with_suffix(path.suffix + ".json"), json.dumps(meta))

    @classmethod
    def load(cls, path: str | Path) -> FaissIndex:
        """Load a snapshot written by :meth:`save`; a damaged file raises InputError."""
        path = Path(path)
        meta_path = path.with_suffix(path.suffix + ".json")
        try:
            meta = json.loads(meta_path.read_text())
            raw = faiss.read_index(str(path))
        except (OSError, ValueError, RuntimeError) as exc:
            raise InputError(f"cannot load index snapshot {path}: {exc}") from None
        obj = cls(int(meta["dim"]), RetrievalConfig(**meta["config"]))
        if raw.d != obj.dim:
            raise InputError(f"index snapshot {path} has dimension {raw.d}, expected {obj.dim}")
        # read_index returns the outer type; the wrapper keeps that object (it owns the
        # C++ index), and only touches downcast views of it for search-time parameters.
        if isinstance(raw, faiss.IndexIDMap2):
            sub = faiss.downcast_index(raw.index)
            if isinstance(sub, faiss.IndexHNSW):
                sub.hnsw.efSearch = obj.config.ef_search
        elif isinstance(raw, faiss.IndexIVF):
            raw.nprobe = obj.config.nprobe
        else:
            raise InputError(f"index snapshot {path} holds an unsupported index type")
        obj._index = raw
        return obj


def merge_hits(lists: list[list[SearchHit]], k: int) -> list[SearchHit]:
    """The union of each list's first ``k`` hits, each id once, ordered by similarity
    (highest first; ties by id): at least as many hits as the longest list's first k."""
    seen: dict[int, SearchHit] = {}
    for hits in lists:
        for h in hits[:k]:
            seen.setdefault(h.id, h)
    return sorted(seen.values(), key=lambda h: (-h.similarity, h.id))


def retrieve(
    index: FaissIndex,
    descriptor: np.ndarray,
    k: int,
    blocks: tuple[int, ...],
    combine: str = "merge",
    among: np.ndarray | None = None,
    variants: np.ndarray | None = None,
) -> list[SearchHit]:
    """One descriptor's candidates: top-k of the whole descriptor, or with several
    ``blocks`` and ``combine="merge"`` the merged top-k of each block
    (:meth:`FaissIndex.search_blocks`, :func:`merge_hits`); with ``variants`` (the
    query's descriptor about displaced centres) by the best similarity over them."""
    if len(blocks) > 1 and combine == "merge":
        lists = index.search_blocks(descriptor, k, blocks, among=among, variants=variants)
        return merge_hits(lists, k)
    if variants is not None and len(variants):
        return index.search_blocks(descriptor, k, (index.dim,), among=among, variants=variants)[0]
    return index.search(descriptor, k, among=among)[0]

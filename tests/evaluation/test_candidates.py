"""The evaluation's candidate lists are the service's retrieval, at every top-k."""

import numpy as np
import pytest

from sgvloc.core.config import RetrievalConfig
from sgvloc.core.features import Features
from sgvloc.core.retrieval import FaissIndex, retrieve
from sgvloc.tools.evaluation.runner import _retrieval


def _unit(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    x = rng.normal(size=shape).astype(np.float32)
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


@pytest.mark.parametrize("blocks", [(16,), (10, 6)], ids=["one block", "two blocks"])
@pytest.mark.parametrize("with_variants", [True, False])
def test_candidates_at_every_k_are_what_retrieve_returns(blocks, with_variants) -> None:
    rng = np.random.default_rng(0)
    dim = sum(blocks)
    db = np.concatenate([_unit(rng, (300, b)) for b in blocks], axis=1) / np.sqrt(len(blocks))
    index = FaissIndex(dim, RetrievalConfig())
    index.add(np.arange(300), db)
    q = np.concatenate([_unit(rng, (b,)) for b in blocks]) / np.sqrt(len(blocks))
    variants = None
    if with_variants:  # the first block about other centres, the rest as the query's
        variants = np.repeat(q[None], 8, axis=0)
        variants[:, : blocks[0]] = _unit(rng, (8, blocks[0])) / np.sqrt(len(blocks))
    no_local = (np.zeros((0, 3), np.float32), np.zeros((0, 8), np.float32))
    query = Features(q, *no_local, None, variants)  # type: ignore[arg-type]
    candidates = _retrieval(index, query, 50, blocks, None)
    for k in (1, 5, 20, 50):
        served = retrieve(index, q, k, blocks, among=None, variants=variants)
        assert [c.keyframe_id for c in candidates(k)] == [h.id for h in served], k
        assert [c.similarity for c in candidates(k)] == [h.similarity for h in served]

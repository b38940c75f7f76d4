"""The localization engine, one module per stage; imports nothing of sgvloc above it
(neither :mod:`sgvloc.server` nor :mod:`sgvloc.tools`) and never FastAPI.

io -> preprocess -> encoders -> retrieval (FAISS) -> rerank (SpectralGV and baselines)
-> pose (RANSAC/ICP), tied together by :class:`sgvloc.core.localizer.Localizer`.
"""

"""The localization engine: one module per stage.

io -> preprocess -> encoders -> retrieval (FAISS) -> rerank (SpectralGV and baselines)
-> pose (RANSAC/ICP), tied together by :class:`sgvloc.core.localizer.Localizer`.
The core never imports FastAPI.
"""

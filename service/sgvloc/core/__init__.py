"""The localization engine, one module per stage; imports neither server, tools nor FastAPI.

io -> preprocess -> encoders -> retrieval (FAISS) -> rerank (SpectralGV and baselines)
-> pose (RANSAC/ICP), tied together by :class:`sgvloc.core.localizer.Localizer`.
"""

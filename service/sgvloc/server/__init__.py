"""What ``sgvloc serve`` runs: the FastAPI app (:mod:`.api`), the map manager, the stores,
metrics, settings and thread limits. Imports :mod:`sgvloc.core`, never :mod:`sgvloc.tools`."""

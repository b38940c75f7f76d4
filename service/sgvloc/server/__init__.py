"""What ``sgvloc serve`` runs (app, map manager, stores, metrics); imports core, never tools."""

"""Offline commands (build-map, eval, synth, train, bench, loadtest); may import server, core."""

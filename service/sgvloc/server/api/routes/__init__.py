"""One router per resource: maps, keyframes, localize, probes."""

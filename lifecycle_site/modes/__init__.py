"""Robot modes: named sets of node target states and parameter values, applied as one run."""

"""Benchmarks of issue 6 (``make bench``): speed and memory of the real stack, measured side
by side in one run. Not part of ``make test``. See docs/performance.md."""

"""Optional py-spy sampling of the gateway, daphne and the ingest process while a scenario measures
(``--profile DIR``), and a summary of such a profile:

    python -m tests.benchmarks.profiling DIR/transition-gateway.txt [--top 25]
"""
from __future__ import annotations

import argparse
import shutil
import signal
import subprocess
import sys
from collections import Counter
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from tests.benchmarks.harness import BenchContext, Stack

SAMPLE_RATE_HZ = 200


def py_spy() -> str:
    found = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    if not Path(found).exists():
        raise SystemExit("--profile needs py-spy: .venv/bin/pip install py-spy")
    return found


@contextmanager
def profiled(ctx: BenchContext, stack: Stack, label: str) -> Iterator[None]:
    """Record the stacks of gateway, daphne and ingest (collapsed, one file each) during the block."""
    if ctx.profile_dir is None:
        yield
        return
    ctx.profile_dir.mkdir(parents=True, exist_ok=True)
    recorders = []
    for child in (stack.gateway, stack.site, stack.ingest):
        assert child is not None
        out = ctx.profile_dir / f"{label}-{child.name}.txt"
        recorders.append(subprocess.Popen(
            [py_spy(), "record", "--pid", str(child.pid), "--rate", str(SAMPLE_RATE_HZ), "--format", "raw",
             "--threads", "--nonblocking", "--output", str(out)],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        ))
    try:
        yield
    finally:
        for recorder in recorders:
            recorder.send_signal(signal.SIGINT)
        for recorder in recorders:
            try:
                recorder.wait(30)
            except subprocess.TimeoutExpired:
                recorder.kill()


def summarize(path: Path, top: int = 25) -> str:
    """Share of samples per thread, then per function: inclusive (on the stack) and self (on top)."""
    inclusive: Counter[str] = Counter()
    own: Counter[str] = Counter()
    threads: Counter[str] = Counter()
    total = 0
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        n = int(count)
        frames = stack.split(";")
        total += n
        threads[frames[0]] += n
        for frame in set(frames[1:]):
            inclusive[frame] += n
        own[frames[-1]] += n
    if not total:
        return f"{path}: no samples"
    out = [f"{path}: {total} samples"]
    for title, counter in (("threads", threads), ("inclusive", inclusive), ("self", own)):
        out.append(f"-- {title}")
        out.extend(f"{100 * n / total:6.1f}%  {frame}" for frame, n in counter.most_common(top))
    return "\n".join(out)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("profile", type=Path)
    parser.add_argument("--top", type=int, default=25)
    options = parser.parse_args()
    print(summarize(options.profile, options.top))

"""``python -m tests.benchmarks [--quick] [--only NAME ...] [--profile DIR]``

Runs the scenarios of issue 6 against the real stack, prints one table per scenario and
writes bench-results.json at the repository root. The ten-minute quiet-fleet scenario runs
only when named (``--only quiet``). Exits 1 if a scenario could not run
(with ``--strict`` also if a target was missed).
"""
from __future__ import annotations

import argparse
import signal
import sys
import tempfile
import time
import traceback
from pathlib import Path
from types import ModuleType

from tests.benchmarks import (
    diagnostics,
    fleet,
    flood,
    load,
    modes,
    networks,
    push,
    quiet,
    scale,
    supervised,
    timeline,
    transition,
)
from tests.benchmarks.harness import BenchContext
from tests.benchmarks.processes import ROOT
from tests.benchmarks.report import ScenarioResult, machine, render_table, write_json
from tests.benchmarks.system import loadavg
from tests.benchmarks.template import DATABASES, Template

SCENARIOS: dict[str, ModuleType] = {
    m.NAME: m for m in (transition, push, scale, flood, networks, load, quiet, timeline, fleet, supervised, modes,
                      diagnostics)
}
ON_REQUEST = {quiet.NAME}  # long: run only with --only


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m tests.benchmarks", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true",
                        help="a short smoke run: fewer samples, 60 nodes, 6 s flood, 60 s quiet fleet")
    parser.add_argument("--only", action="append", choices=sorted(SCENARIOS), metavar="NAME",
                        help=f"run only this scenario (repeatable): {', '.join(SCENARIOS)}; "
                             f"{', '.join(sorted(ON_REQUEST))} runs only when named")
    parser.add_argument("--output", type=Path, default=ROOT / "bench-results.json")
    parser.add_argument("--profile", type=Path, metavar="DIR",
                        help="sample the gateway and daphne with py-spy while measuring; files go to DIR")
    parser.add_argument("--database", choices=DATABASES, default="sqlite",
                        help="the site's database: SQLite files, or a throw-away PostgreSQL cluster (Debian's "
                             "postgresql), one database per scenario")
    parser.add_argument("--web-processes", type=int, metavar="N",
                        help="daphne processes of the site (LIFECYCLE_WEB_PROCESSES) in every scenario; without it "
                             "1, as installed, and the load scenario runs with 1 and with 2")
    parser.add_argument("--keep", action="store_true", help="keep the work dir (databases, process logs)")
    parser.add_argument("--strict", action="store_true", help="exit 1 when a target is missed")
    return parser.parse_args(argv)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt  # unwinds through every stack's teardown


def _run_all(names: list[str], ctx: BenchContext) -> tuple[list[ScenarioResult], list[str]]:
    """Every scenario named, in order: their results, and the names of those that could not run."""
    results: list[ScenarioResult] = []
    failed: list[str] = []
    for name in names:
        module = SCENARIOS[name]
        started = time.monotonic()
        try:
            result = module.run(ctx)
        except Exception:
            failed.append(name)
            result = ScenarioResult(name, module.TITLE, load_before=loadavg())
            result.notes.append("could not run: " + traceback.format_exc(limit=3).strip().splitlines()[-1])
            traceback.print_exc()
        result.seconds = time.monotonic() - started
        results.append(result)
        print("\n" + render_table(result), flush=True)
    return results, failed


def main(argv: list[str]) -> int:
    options = parse(argv)
    signal.signal(signal.SIGTERM, _interrupt)
    names = options.only or [name for name in SCENARIOS if name not in ON_REQUEST]
    workdir = Path(tempfile.mkdtemp(prefix="lifecycle-bench-"))
    print(f"benchmarks: {', '.join(names)}{' (quick)' if options.quick else ''} on {options.database}; "
          f"work dir {workdir}", flush=True)
    began = time.monotonic()
    measured_on = machine()
    template = Template(workdir, options.database)
    try:
        context = BenchContext(workdir, template, options.quick, options.profile, options.web_processes)
        results, failed = _run_all(names, context)
    finally:
        template.close()
    write_json(options.output, results, {"quick": options.quick, "only": options.only,
                                         "database": options.database,
                                         "web_processes": options.web_processes}, measured_on)
    missed = [f"{r.name}: {c.name}" for r in results for c in r.checks if not c.met]
    print(f"\n{len(results) - len(failed)} of {len(names)} scenarios ran in {time.monotonic() - began:.0f} s; "
          f"results in {options.output}")
    if missed:
        print("targets missed:\n  " + "\n  ".join(missed))
    if failed:
        print(f"could not run: {', '.join(failed)} (process logs kept in {workdir})")
    elif not options.keep:
        import shutil

        shutil.rmtree(workdir, ignore_errors=True)
    return 1 if failed or (options.strict and missed) else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

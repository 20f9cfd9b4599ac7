"""Results of a benchmark run: sample series, single figures, checks against the targets,
printed as one table per scenario and written as JSON."""
from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


def percentile(values: list[float], q: float) -> float:
    """The q-th percentile (0-100) with linear interpolation between the closest ranks."""
    if not values:
        return math.nan
    ordered = sorted(values)
    rank = (len(ordered) - 1) * q / 100
    low, high = math.floor(rank), math.ceil(rank)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


@dataclass
class Series:
    """Repeated measurements of one thing (milliseconds unless said otherwise)."""

    name: str
    values: list[float] = field(default_factory=list)
    unit: str = "ms"

    def add(self, value: float) -> None:
        self.values.append(value)

    @property
    def median(self) -> float:
        return percentile(self.values, 50)

    def summary(self) -> dict[str, Any]:
        return {
            "unit": self.unit,
            "n": len(self.values),
            "median": percentile(self.values, 50),
            "p95": percentile(self.values, 95),
            "p99": percentile(self.values, 99),
            "min": min(self.values, default=math.nan),
            "max": max(self.values, default=math.nan),
            "values": [round(v, 3) for v in self.values],
        }


@dataclass
class Check:
    """One target of issue 6: the measured figure, the target as text, met or missed."""

    name: str
    value: float
    target: str
    met: bool
    unit: str = ""


@dataclass
class ScenarioResult:
    name: str
    title: str
    series: list[Series] = field(default_factory=list)
    figures: dict[str, tuple[float, str]] = field(default_factory=dict)  # name -> (value, unit)
    checks: list[Check] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    load_before: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seconds: float = 0.0

    def new_series(self, name: str, unit: str = "ms") -> Series:
        series = Series(name, unit=unit)
        self.series.append(series)
        return series

    def figure(self, name: str, value: float, unit: str = "") -> float:
        self.figures[name] = (value, unit)
        return value

    def check(self, name: str, value: float, target: str, met: bool, unit: str = "") -> None:
        self.checks.append(Check(name, value, target, bool(met) and not math.isnan(value), unit))

    def as_dict(self) -> dict[str, Any]:
        return {
            "title": self.title,
            "seconds": round(self.seconds, 1),
            "load_before": self.load_before,
            "series": {s.name: s.summary() for s in self.series},
            "figures": {k: {"value": v, "unit": u} for k, (v, u) in self.figures.items()},
            "checks": [c.__dict__ for c in self.checks],
            "notes": self.notes,
        }


def _fmt(value: float) -> str:
    if math.isnan(value):
        return "-"
    if abs(value) >= 1000:
        return f"{value:,.0f}"
    if abs(value) >= 10:
        return f"{value:.1f}"
    return f"{value:.2f}"


def render_table(result: ScenarioResult) -> str:
    """The scenario as plain text: series (n, median, p95, p99), figures, then the checks."""
    lines = [f"== {result.title} ({result.seconds:.0f} s, load before {result.load_before[0]:.2f})"]
    if result.series:
        width = max(len(s.name) for s in result.series) + 2
        lines.append(f"{'series':<{width}}{'n':>6}{'median':>11}{'p95':>11}{'p99':>11}  unit")
        for s in result.series:
            d = s.summary()
            lines.append(
                f"{s.name:<{width}}{d['n']:>6}{_fmt(d['median']):>11}{_fmt(d['p95']):>11}{_fmt(d['p99']):>11}  {s.unit}"
            )
    if result.figures:
        width = max(len(k) for k in result.figures) + 2
        for name, (value, unit) in result.figures.items():
            lines.append(f"{name:<{width}}{_fmt(value):>11}  {unit}")
    if result.checks:
        width = max(len(c.name) for c in result.checks) + 2
        lines.append(f"{'target':<{width}}{'measured':>12}  {'goal':<14}verdict")
        for c in result.checks:
            measured = f"{_fmt(c.value)} {c.unit}".strip()
            lines.append(f"{c.name:<{width}}{measured:>12}  {c.target:<14}{'met' if c.met else 'MISSED'}")
    lines.extend(f"note: {n}" for n in result.notes)
    return "\n".join(lines)


def machine() -> dict[str, Any]:
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=Path(__file__).parent
    ).stdout.strip()
    cpu = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "date": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "cpus": os.cpu_count(),
        "cpu_model": cpu,
        "python": platform.python_version(),
        "kernel": platform.release(),
        "commit": commit,
    }


def write_json(path: Path, results: list[ScenarioResult], options: dict[str, Any], machine: dict[str, Any]) -> None:
    """``machine`` as read when the run began (the commit then is the one measured)."""
    body = {
        "machine": machine,
        "options": options,
        "scenarios": {r.name: r.as_dict() for r in results},
    }
    path.write_text(json.dumps(_clean(body), indent=2, default=str, allow_nan=False) + "\n")


def _clean(value: Any) -> Any:
    """NaN (a figure that could not be measured) becomes null, as JSON has no NaN."""
    if isinstance(value, float):
        return None if math.isnan(value) or math.isinf(value) else round(value, 3)
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value

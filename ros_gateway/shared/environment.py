"""Settings from environment variables, for the site (lifecycle_site/settings.py) and the
gateway (ros_gateway/config.py) alike: unset or empty gives the default; a value that cannot be
meant raises SettingError naming the variable, what it holds and the form it needs (a typo must
not silently mean a default, nor stop a process with a bare "could not convert string to float").
"""
from __future__ import annotations

import math
import os
from collections.abc import Mapping

TRUE, FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")


class SettingError(ValueError):
    """An environment variable's value is unusable; the message says which and what would do."""


def _raw(name: str, environ: Mapping[str, str] | None) -> str:
    return (os.environ if environ is None else environ).get(name, "").strip()


def text(name: str, default: str = "", environ: Mapping[str, str] | None = None) -> str:
    return _raw(name, environ) or default


def _outside(value: float, above: float | None, minimum: float | None, maximum: float | None) -> bool:
    return ((above is not None and value <= above) or (minimum is not None and value < minimum)
            or (maximum is not None and value > maximum))


def _refusal(name: str, raw: str, what: str, example: float, show, *, above: float | None = None,
             minimum: float | None = None, maximum: float | None = None) -> SettingError:
    """``NAME='raw': expected WHAT, more than A and at most B (e.g. EXAMPLE).``"""
    bounds = [f"more than {show(above)}" if above is not None else "",
              f"at least {show(minimum)}" if minimum is not None else "",
              f"at most {show(maximum)}" if maximum is not None else ""]
    wanted = " and ".join(b for b in bounds if b)
    return SettingError(f"{name}={raw!r}: expected {what}" + (f", {wanted}" if wanted else "")
                        + f" (e.g. {show(example)}).")


def number(name: str, default: float, *, minimum: float | None = None, maximum: float | None = None,
           above: float | None = None, unit: str = "seconds", example: float | None = None,
           environ: Mapping[str, str] | None = None) -> float:
    """A finite number, within the bounds given (``above``: strictly more than)."""
    raw = _raw(name, environ)
    if not raw:
        return float(default)
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or _outside(value, above, minimum, maximum):
        raise _refusal(name, raw, f"a number of {unit}", default if example is None else example,
                       lambda x: f"{x:g}", above=above, minimum=minimum, maximum=maximum)
    return value


def whole(name: str, default: int, *, minimum: int | None = None, maximum: int | None = None,
          unit: str = "", environ: Mapping[str, str] | None = None) -> int:
    """A whole number, within the bounds given."""
    raw = _raw(name, environ)
    if not raw:
        return default
    try:
        value = int(raw)
    except ValueError:
        value = None
    if value is None or _outside(value, None, minimum, maximum):
        raise _refusal(name, raw, f"a whole number{f' of {unit}' if unit else ''}", default, str,
                       minimum=minimum, maximum=maximum)
    return value


def flag(name: str, default: bool, environ: Mapping[str, str] | None = None) -> bool:
    raw = _raw(name, environ)
    if not raw:
        return default
    if raw.lower() in TRUE:
        return True
    if raw.lower() in FALSE:
        return False
    raise SettingError(f"{name}={raw!r}: expected true or false (also 1/0, yes/no, on/off).")


def items(name: str, default: str = "", environ: Mapping[str, str] | None = None) -> list[str]:
    """A comma-separated list, blanks dropped."""
    return [item.strip() for item in (_raw(name, environ) or default).split(",") if item.strip()]


def megabytes(name: str, environ: Mapping[str, str] | None = None) -> int | None:
    """A size in MB, as bytes; unset is None (no limit of ours)."""
    if not _raw(name, environ):
        return None
    size = number(name, 0, above=0, maximum=1_000_000, unit="MB", example=16, environ=environ)
    return int(size * 1024 * 1024)


def agreed(environ: Mapping[str, str] | None = None) -> dict:
    """What the site and its gateways both read (times in seconds), each from its own environment;
    the site's settings.LIFECYCLE holds them, a gateway's config.py reads them here too."""
    return {
        # Bound on every lifecycle/parameter service call the gateway makes.
        "SERVICE_TIMEOUT": number("LIFECYCLE_SERVICE_TIMEOUT", 5.0, above=0, maximum=60, environ=environ),
        # How often the gateway re-reads the ROS graph and the robot table.
        "DISCOVERY_INTERVAL": number("LIFECYCLE_DISCOVERY_INTERVAL", 0.5, above=0, environ=environ),
        "ROBOT_REFRESH_INTERVAL": number("LIFECYCLE_ROBOT_REFRESH_INTERVAL", 2.0, above=0, environ=environ),
        # The gateway writes a heartbeat; the site calls it offline when it is older than this.
        "HEARTBEAT_INTERVAL": number("LIFECYCLE_HEARTBEAT_INTERVAL", 2.0, above=0, environ=environ),
        # A robot process that misses two get_state probes in a row is unreachable (its host's
        # link may be down): seen in about 4 s instead of the DDS lease's 20+ s. 0 turns it off.
        "LIVENESS_INTERVAL": number("LIFECYCLE_LIVENESS_INTERVAL", 1.0, minimum=0, environ=environ),
        "LIVENESS_TIMEOUT": number("LIFECYCLE_LIVENESS_TIMEOUT", 1.5, above=0, environ=environ),
        # In-memory log buffer of the gateway; records beyond it are dropped and counted.
        "LOG_BUFFER": whole("LIFECYCLE_LOG_BUFFER", 20000, minimum=1, unit="log records", environ=environ),
    }

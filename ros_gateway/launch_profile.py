"""A launch profile: how the gateway starts one of a robot's processes (supervisor.py runs it), read from the
site's configuration with every field checked (a profile is input from the site: ValueError names what is wrong).
"""
from __future__ import annotations

import re
import signal
from dataclasses import dataclass

MAX_TEXT, MAX_ITEMS, MAX_SECONDS, MAX_WINDOW_S, MAX_FAILURES = 4096, 256, 300.0, 7 * 86400.0, 10_000
NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")


@dataclass(frozen=True)
class LaunchProfile:
    robot: str
    name: str  # 1-64 chars of [A-Za-z0-9_.-]
    command: str  # the executable (absolute path or a name found on PATH)
    args: tuple[str, ...] = ()
    env: tuple[tuple[str, str], ...] = ()  # added to the gateway's own environment
    cwd: str | None = None
    respawn: bool = True
    respawn_delay: float = 1.0  # doubles for each exit in a row within MIN_UPTIME_S, up to MAX_RESPAWN_DELAY_S
    stop_signal: int = signal.SIGTERM  # SIGTERM or SIGINT
    stop_grace: float = 10.0  # seconds after stop_signal before SIGKILL
    max_failures: int = 5  # exits (not asked for) within failure_window ...
    failure_window: float = 300.0  # ... after which respawning stops ("given_up") until started by request

    @classmethod
    def from_config(cls, robot: str, data: object) -> LaunchProfile:
        """From the site's JSON: name, command and the other fields optional (null as absent; env an object, stop_signal
        "SIGTERM" or "SIGINT"). ValueError, naming the field and what it must be, for anything malformed."""
        if not isinstance(data, dict):
            raise ValueError("a launch profile must be a JSON object")
        data = {key: value for key, value in data.items() if value is not None}
        if not NAME.fullmatch(name := _text(data.get("name"), "name")):
            raise ValueError("name must be 1-64 characters of A-Z, a-z, 0-9, '_', '.' and '-'")
        args, env, cwd = data.get("args", []), data.get("env", {}), data.get("cwd")
        if not isinstance(args, list) or len(args) > MAX_ITEMS:
            raise ValueError(f"args must be a list of at most {MAX_ITEMS} strings")
        if not isinstance(env, dict) or len(env) > MAX_ITEMS or any("=" in _text(key, "env's names") for key in env):
            raise ValueError(f"env must be an object of at most {MAX_ITEMS} names (without '=') and string values")
        if (stop_signal := data.get("stop_signal", "SIGTERM")) not in ("SIGTERM", "SIGINT"):
            raise ValueError('stop_signal must be "SIGTERM" or "SIGINT"')
        if not isinstance(respawn := data.get("respawn", True), bool):
            raise ValueError("respawn must be true or false")
        if type(failures := data.get("max_failures", 5)) is not int or not 1 <= failures <= MAX_FAILURES:
            raise ValueError(f"max_failures must be a whole number from 1 to {MAX_FAILURES}")
        return cls(robot, name, _text(data.get("command"), "command"),
                   tuple(_text(arg, f"args[{n}]", empty=True) for n, arg in enumerate(args)),
                   tuple(sorted((key, _text(value, f"env[{key!r}]", empty=True)) for key, value in env.items())),
                   None if cwd is None else _text(cwd, "cwd"), respawn, _seconds(data, "respawn_delay", 1.0),
                   signal.Signals[stop_signal], _seconds(data, "stop_grace", 10.0), failures,
                   _seconds(data, "failure_window", 300.0, MAX_WINDOW_S))


def _text(value: object, what: str, *, empty: bool = False) -> str:
    if not isinstance(value, str) or (not value and not empty) or "\0" in value or len(value) > MAX_TEXT:
        raise ValueError(f"{what} must be a{'' if empty else ' non-empty'} string of at most {MAX_TEXT} chars, no NUL")
    return value


def _seconds(data: dict, key: str, default: float, most: float = MAX_SECONDS) -> float:
    if type(value := data.get(key, default)) not in (int, float) or not 0 <= value <= most:  # NaN, infinity too
        raise ValueError(f"{key} must be a number of seconds from 0 to {most:g}")
    return float(value)

"""What the ingest process reads from Redis, as plain values: stream entry ids, an entry's
JSON payload, whether a reply carried it, gaps in a gateway's fact sequence, and a heartbeat
as a Gateway row's fields."""
from __future__ import annotations

import json
from datetime import datetime, timedelta, timezone
from typing import Any

from lifecycle_site.gateway_link.gateway_input import FactRejected, parse_time
from ros_gateway.shared import protocol


def text(raw: bytes | str) -> str:
    """A stream name or entry id as redis-py hands it over (bytes unless decoded) as text."""
    return raw.decode() if isinstance(raw, bytes) else raw


def entry_id(raw: bytes | str) -> tuple[int, int]:
    ms, _, seq = text(raw).partition("-")
    return int(ms), int(seq or 0)


def is_after(raw: bytes | str, cursor: str) -> bool:
    return not cursor or entry_id(raw) > entry_id(cursor)


def replied(fields: dict) -> bool:
    """Whether a facts entry was handed over with a command's reply (protocol.REPLIED)."""
    return bool(fields.get(protocol.REPLIED.encode(), fields.get(protocol.REPLIED)))


def decode(fields: dict) -> dict:
    """An entry's payload (field "f", JSON); raises FactRejected."""
    raw = fields.get(b"f", fields.get("f"))
    try:
        data = json.loads(raw)
    except (TypeError, ValueError, RecursionError) as exc:  # (JSON nested deeper than Python's stack)
        raise FactRejected(f"an entry without a JSON field 'f' ({type(exc).__name__})") from None
    if not isinstance(data, dict):
        raise FactRejected("an entry's 'f' must be a JSON object")
    return data


MAX_SEQ = 2**53  # a gateway's fact numbers (a database's 64-bit integer holds them; JSON's exact integers)


def count_gap(instance: Any, seq: Any, last_instance: str, last_seq: int) -> tuple[int, str, int]:
    """Entries missing before this one (trimmed from Redis before they were read), and the new
    (instance, seq) to remember. Sequences start at 1 with every gateway process."""
    if not isinstance(seq, int) or isinstance(seq, bool) or not 1 <= seq <= MAX_SEQ \
            or not isinstance(instance, str) or not 0 < len(instance) <= 32:
        return 0, last_instance, last_seq
    if instance != last_instance:
        return seq - 1, instance, seq
    if seq <= last_seq:
        return 0, last_instance, last_seq  # seen already
    return seq - last_seq - 1, instance, seq


# A gateway's clock may run a little ahead of the site's. A beat's time further ahead, or
# before 2000, is wrong: "at": 9999999999 (year 2286) would keep a dead gateway online for good.
MAX_CLOCK_SKEW = timedelta(minutes=5)
EARLIEST_BEAT = datetime(2000, 1, 1, tzinfo=timezone.utc)


def plausible(moment: datetime | None) -> datetime | None:
    """The time, if a heartbeat could carry it (EARLIEST_BEAT up to MAX_CLOCK_SKEW ahead); else None."""
    if moment is None or not EARLIEST_BEAT <= moment <= datetime.now(timezone.utc) + MAX_CLOCK_SKEW:
        return None
    return moment


def beat_at(value: Any) -> datetime | None:
    """A heartbeat's "at" (seconds since the epoch) as a time, if plausible."""
    if isinstance(value, bool):
        return None
    try:
        return plausible(datetime.fromtimestamp(float(value), timezone.utc))
    except (TypeError, ValueError, OverflowError, OSError):
        return None


def beat_started(value: Any) -> datetime | None:
    """A heartbeat's "started" (ISO 8601) as a time, if plausible."""
    try:
        return plausible(parse_time(value))
    except FactRejected:
        return None


def beat_fields(beat: dict) -> dict[str, Any]:
    """The Gateway row's copy of a heartbeat (what is malformed or implausible is left out)."""
    fields: dict[str, Any] = {}
    if (at := beat_at(beat.get("at"))) is not None:
        fields["last_beat"] = at
    if (started := beat_started(beat.get("started"))) is not None:
        fields["started"] = started
    fields["stopped"] = bool(beat.get("stopped"))
    for name, size in (("instance", 32), ("version", 64), ("host", 255)):
        if isinstance(beat.get(name), str):
            fields[name] = beat[name][:size]
    if isinstance(beat.get("pid"), int) and beat["pid"] >= 0:
        fields["pid"] = beat["pid"]
    if isinstance(beat.get("nodes"), int) and beat["nodes"] >= 0:
        fields["node_count"] = beat["nodes"]
    if isinstance(beat.get("domains"), list):
        fields["domains"] = [d for d in beat["domains"] if isinstance(d, int)]
    for name in ("dds", "outbox"):
        if isinstance(beat.get(name), dict):
            fields[name] = beat[name]
    return fields

"""How long the ingest process holds the database: its write transactions, and its pause after each.

A write transaction of the ingest (SQLite: the database's one write lock) holds at most
FACTS_PER_TRANSACTION facts or about LOG_RECORDS_PER_TRANSACTION log records; then it commits and
the next one begins, so that a request of the site never waits long for it, and a frozen ingest
holds as little as it can (docs/architecture.md, "A frozen writer").
"""
from __future__ import annotations

from ros_gateway.shared import protocol

FACTS_PER_TRANSACTION = 100
LOG_RECORDS_PER_TRANSACTION = 2000
# SQLite serves waiting writers by polling (up to every 100 ms), not in turn: after each
# transaction the ingest pauses for this share of its length, at most MAX_YIELD_S.
YIELD_SHARE, MAX_YIELD_S = 0.5, 0.05


def transactions(kind: str, entries: list) -> list[list]:
    """The entries in groups that each make one short transaction."""
    if kind == "facts":
        return [entries[i:i + FACTS_PER_TRANSACTION] for i in range(0, len(entries), FACTS_PER_TRANSACTION)]
    chunks: list[list] = [[]]
    records = 0
    for entry, fields in entries:
        size = protocol.LOG_BATCH  # a batch's records, at most (not decoded yet)
        if chunks[-1] and records + size > LOG_RECORDS_PER_TRANSACTION:
            chunks.append([])
            records = 0
        chunks[-1].append((entry, fields))
        records += size
    return chunks

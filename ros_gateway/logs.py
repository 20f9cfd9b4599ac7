"""/rosout records: from the executor threads into a bounded buffer, then in batches to the
database (pruned to a bounded history) and to the robots' and nodes' live groups."""
from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from datetime import datetime, timedelta
from typing import TYPE_CHECKING

from lifecycle_site.fleet.models import LogRecord
from ros_gateway import store
from ros_gateway.shared import protocol
from ros_gateway.store import LogRow, db
from ros_gateway.streams import LogBuffer, LogEntry, logger_to_node_name, owning_node

if TYPE_CHECKING:
    from ros_gateway.service import Gateway, LiveNode

log = logging.getLogger(__name__)

FLUSH_INTERVAL_S = 0.1
BATCH_LIMIT = 2000
PUSH_CHUNK = 200
PRUNE_INTERVAL_S = 60.0
ERROR_LEVEL = 40
LEVEL_NAMES = dict(LogRecord.LEVELS)


class LogPipeline:
    def __init__(self, gateway: "Gateway") -> None:
        self.gateway = gateway
        self.buffer = LogBuffer(gateway.config["LOG_BUFFER"])
        # Latest ERROR/FATAL lines per node key: the "why" of a failed transition.
        self.recent_errors: dict[str, deque[LogEntry]] = {}
        self.stored = 0

    def on_log(self, domain_id: int, msg) -> None:
        """Called on an executor thread for every /rosout message: copy and hand over."""
        try:
            self.buffer.append(LogEntry.from_msg(domain_id, msg))
        except Exception:
            log.exception("ignored a malformed /rosout message")

    async def run(self, stopping: asyncio.Event) -> None:
        last_prune = time.monotonic()
        while not stopping.is_set():
            try:
                await self.flush()
                if time.monotonic() - last_prune > PRUNE_INTERVAL_S:
                    last_prune = time.monotonic()
                    config = self.gateway.config
                    deleted = await db(store.prune_logs)(config["LOG_KEEP_PER_NODE"], config["LOG_KEEP_HOURS"])
                    if deleted:
                        log.info("pruned %d old log records", deleted)
            except Exception:
                log.exception("storing log records failed; continuing")
            await asyncio.sleep(FLUSH_INTERVAL_S)

    async def flush(self) -> None:
        while len(self.buffer):
            batch = self.buffer.drain(BATCH_LIMIT)
            rows, nodes = self._to_rows(batch)
            if not rows:
                continue
            ids = await db(store.insert_logs)(rows)
            self.stored += len(ids)
            await self._push(rows, ids, nodes)

    def _to_rows(self, batch: list[LogEntry]) -> tuple[list[LogRow], list["LiveNode | None"]]:
        rows, nodes = [], []
        by_robot: dict[int, dict[str, "LiveNode"]] = {}
        for node in self.gateway.nodes.values():
            by_robot.setdefault(node.robot.id, {})[node.name] = node
        for entry in batch:
            robot = self.gateway.robot_for(entry.domain_id, logger_to_node_name(entry.logger))
            if robot is None:
                continue
            robot_nodes = by_robot.get(robot.id, {})
            owner = owning_node(entry.logger, set(robot_nodes))
            node = robot_nodes.get(owner) if owner else None
            if node is not None and entry.level >= ERROR_LEVEL:
                self.recent_errors.setdefault(node.key, deque(maxlen=20)).append(entry)
            rows.append(
                LogRow(
                    robot.id,
                    node.row.id if node else None,
                    entry.logger[:255],
                    entry.stamp,
                    entry.level if entry.level in LEVEL_NAMES else LogRecord.INFO,
                    entry.message,
                    entry.file[:255],
                    entry.function[:255],
                    max(entry.line, 0),
                )
            )
            nodes.append(node)
        return rows, nodes

    async def _push(self, rows: list[LogRow], ids: list[int], nodes: list["LiveNode | None"]) -> None:
        per_group: dict[str, list[dict]] = {}
        for row, row_id, node in zip(rows, ids, nodes, strict=True):
            # LogRecord.as_dict() of the stored record, plus the node's key (no model instances).
            payload = {
                "id": row_id,
                "stamp": row.stamp.isoformat(),
                "level": LEVEL_NAMES[row.level],
                "logger": row.logger,
                "message": row.message,
                "file": row.file,
                "function": row.function,
                "line": row.line,
                "node_id": node.key if node else None,
            }
            per_group.setdefault(protocol.robot_group(row.robot_id), []).append(payload)
            if node is not None:
                per_group.setdefault(protocol.node_group(node.key), []).append(payload)
        for group, records in per_group.items():
            for start in range(0, len(records), PUSH_CHUNK):
                chunk = records[start : start + PUSH_CHUNK]
                await self.gateway.relay.publish([group], {"type": "node.logs", "records": chunk})

    def errors_since(self, node_key: str, since: datetime) -> list[LogEntry]:
        slack = since - timedelta(milliseconds=100)
        return [e for e in self.recent_errors.get(node_key, ()) if e.stamp >= slack]

"""/rosout records: from the executor threads into a bounded buffer, then in batches to the
site's log stream (outbox.py), where the ingest process stores and relays them. The latest
ERROR/FATAL lines of each node stay here too: they are the "why" of a failed transition."""
from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import deque
from datetime import datetime, timedelta, timezone

from ros_gateway.outbox import Outbox
from ros_gateway.registry import LiveNode, NodeRegistry
from ros_gateway.shared import protocol
from ros_gateway.topic_messages import LogBuffer, LogEntry, logger_to_node_name, owning_node

log = logging.getLogger(__name__)

# After a record arrives, the others arriving this long after it go in the same batch.
COLLECT_INTERVAL_S = 0.1
IDLE_BOUND_S = 5.0  # a safeguard: records wake the collector (_wake)
ERROR_LEVEL = 40
LEVELS = (10, 20, 30, 40, 50)
INFO = 20


class LogPipeline:
    def __init__(self, registry: NodeRegistry, outbox: Outbox, buffer_limit: int) -> None:
        self.registry = registry
        self.outbox = outbox
        self.buffer = LogBuffer(buffer_limit)
        # Supervised processes' output lines, as rows, bounded like the buffer (oldest dropped).
        self.output: deque[list] = deque(maxlen=max(1, buffer_limit // 4))
        self.output_dropped = 0
        self.recent_errors: dict[str, deque[LogEntry]] = {}
        self.collected = 0
        self._reported_drops = 0
        # Quiet logs cost nothing: the collector sleeps until a record comes. ``_asleep`` is
        # set before it looks at the buffers one last time, and a thread that appended looks at
        # it after: one of the two sees the other's record (no wake-up lost, none per record).
        self._wake = asyncio.Event()
        self._asleep = False
        self._loop: asyncio.AbstractEventLoop | None = None

    def on_log(self, domain_id: int, msg) -> None:
        """Called on an executor thread for every /rosout message: copy and hand over."""
        try:
            self.buffer.append(LogEntry.from_msg(domain_id, msg))
        except Exception:
            log.exception("ignored a malformed /rosout message")
            return
        if self._asleep and self._loop is not None:
            self._asleep = False
            try:
                self._loop.call_soon_threadsafe(self._wake.set)
            except RuntimeError:  # the loop has closed: the gateway is stopping
                pass

    def on_output(self, robot: str, process: str, stream: str, line: str) -> None:
        """A line a supervised process wrote (supervisor.py): a record of its robot's log, under
        the logger "PROCESS/stdout" or "PROCESS/stderr"."""
        if len(self.output) == self.output.maxlen:
            self.output_dropped += 1
        self.output.append([robot, "", f"{process}/{stream}"[:255], datetime.now(timezone.utc).isoformat(), INFO,
                            line, "", "", 0])
        self._wake.set()  # on the gateway's loop (supervisor.py reads the output there)

    async def run(self, stopping: asyncio.Event) -> None:
        self._loop = asyncio.get_running_loop()
        while not stopping.is_set():
            try:
                self.collect()
            except Exception:
                log.exception("collecting log records failed; continuing")
            await asyncio.sleep(COLLECT_INTERVAL_S)
            self._wake.clear()
            self._asleep = True
            if not self.output and not len(self.buffer):
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), IDLE_BOUND_S)
            self._asleep = False

    def collect(self) -> None:
        """Move what the buffer holds into log batches for the site (never blocks)."""
        while self.output:
            rows = [self.output.popleft() for _ in range(min(len(self.output), protocol.LOG_BATCH))]
            dropped, self.output_dropped = self.output_dropped, 0
            self.outbox.emit_logs(rows, dropped=dropped)
            self.collected += len(rows)
        while len(self.buffer):
            rows = self._to_rows(self.buffer.drain(protocol.LOG_BATCH))
            dropped = self.buffer.dropped - self._reported_drops
            self._reported_drops += dropped
            if rows or dropped:
                self.outbox.emit_logs(rows, dropped=dropped)
                self.collected += len(rows)

    def _to_rows(self, batch: list[LogEntry]) -> list[list]:
        rows = []
        by_robot: dict[int, dict[str, LiveNode]] = {}
        for node in self.registry.nodes.values():
            by_robot.setdefault(node.robot.id, {})[node.name] = node
        for entry in batch:
            robot = self.registry.robot_for(entry.domain_id, logger_to_node_name(entry.logger))
            if robot is None:
                continue
            robot_nodes = by_robot.get(robot.id, {})
            owner = owning_node(entry.logger, set(robot_nodes))
            node = robot_nodes.get(owner) if owner else None
            if node is not None and entry.level >= ERROR_LEVEL:
                self.recent_errors.setdefault(node.key, deque(maxlen=20)).append(entry)
            rows.append([
                robot.name,
                node.name if node else "",
                entry.logger[:255],
                entry.stamp.isoformat(),
                entry.level if entry.level in LEVELS else INFO,
                entry.message,
                entry.file[:255],
                entry.function[:255],
                max(entry.line, 0),
            ])
        return rows

    def errors_since(self, node_key: str, since: datetime) -> list[LogEntry]:
        slack = since - timedelta(milliseconds=100)
        return [e for e in self.recent_errors.get(node_key, ()) if e.stamp >= slack]

"""Parameters of managed nodes: listing, checked setting, and every change made by anyone
(seen on /parameter_events) recorded with its old and new value and pushed live."""
from __future__ import annotations

import logging
import time
from datetime import datetime, timezone
from typing import TYPE_CHECKING, Any

from lifecycle_site.audit.models import ParameterRecord
from ros_gateway.parameters import from_msg, list_parameters, set_parameters, type_of
from ros_gateway.shared import param_types as pt
from ros_gateway.shared import protocol
from ros_gateway.store import db

if TYPE_CHECKING:
    from ros_gateway.service import Gateway, LiveNode

log = logging.getLogger(__name__)

# How long a value we set waits for its /parameter_events echo before it counts as someone else's.
ECHO_WINDOW_S = 10.0


def _record(node: "LiveNode", name: str, old: Any, new: Any, outcome: str, reason: str, source: str,
            user_id: int | None) -> dict:
    # A NaN or infinite value (a dynamically typed parameter may hold one) is kept as its text:
    # the JSON columns refuse it, and the record must not be lost.
    record = ParameterRecord(
        node_id=node.row.id, robot_name=node.robot.name, node_name=node.name, name=name, old_value=pt.storable(old),
        new_value=pt.storable(new), outcome=outcome, reason=reason, source=source, requested_by_id=user_id,
        at=datetime.now(timezone.utc),
    )
    record.save()  # fills in the user's name
    return record.as_dict()


class ParameterKeeper:
    def __init__(self, gateway: "Gateway") -> None:
        self.gateway = gateway
        # node key -> {parameter name: listing entry}; filled on first use
        self.cache: dict[str, dict[str, dict]] = {}
        # node key -> {parameter name: (value we set, until when we expect its echo)}
        self.expected: dict[str, dict[str, tuple[Any, float]]] = {}

    async def listing(self, node: "LiveNode", timeout: float) -> list[dict]:
        domain = self.gateway.domains[node.robot.domain_id]
        parameters = await list_parameters(domain, node.name, timeout)
        self.cache[node.key] = {p["name"]: p for p in parameters}
        return parameters

    async def set(self, node: "LiveNode", values: dict, timeout: float, source: str, user_id: int | None) -> list[dict]:
        """Check each value against the node's descriptors, send the good ones together, and
        record every outcome. Returns one result per requested name, in request order."""
        known = self.cache.get(node.key) or {p["name"]: p for p in await self.listing(node, timeout)}
        # Taken now: the node's /parameter_events echo may update the cache before it answers.
        olds = {name: known.get(name, {}).get("value") for name in values}
        results: dict[str, dict] = {}
        to_send: dict[str, tuple[Any, str]] = {}
        for name, value in values.items():
            entry = known.get(name)
            if entry is None:
                results[name] = {"successful": False, "reason": f"{node.name} has no parameter {name!r}"}
                continue
            try:
                coerced = pt.check(value, entry)
                type_name = entry["type"] if entry["type"] != "not set" else type_of(coerced)
            except pt.InvalidValue as exc:
                results[name] = {"successful": False, "reason": f"{name} {exc}"}
                continue
            to_send[name] = (coerced, type_name)
        if to_send:
            until = time.monotonic() + ECHO_WINDOW_S
            self.expected.setdefault(node.key, {}).update({n: (v, until) for n, (v, _) in to_send.items()})
            domain = self.gateway.domains[node.robot.domain_id]
            for answer in await set_parameters(domain, node.name, to_send, timeout):
                name = answer["name"]
                results[name] = {"successful": answer["successful"],
                                 "reason": answer["reason"] or ("" if answer["successful"] else "refused by the node")}
                if not answer["successful"]:
                    self.expected.get(node.key, {}).pop(name, None)
        ordered = []
        changes = []
        for name, value in values.items():
            result = results[name]
            old = olds[name]
            new = to_send[name][0] if name in to_send else value
            if result["successful"]:
                known[name] = {**known[name], "value": new}
                changes.append({"name": name, "old": old, "new": new})
            try:
                await db(_record)(node, name, old, new, "succeeded" if result["successful"] else "rejected",
                                  result["reason"], source, user_id)
            except Exception:  # the database: the records of the other values must still be written
                log.exception("the change of parameter %r of %s:%s (%s) could not be recorded in the audit log",
                              name, node.robot.name, node.name, "set" if result["successful"] else "refused")
            ordered.append({"name": name, "old": old, "new": new, **result})
        if changes:
            await self._push(node, changes)
        return ordered

    def on_event(self, domain_id: int, msg) -> None:
        """/parameter_events of one domain (on the gateway loop)."""
        node = self.gateway.nodes.get((domain_id, msg.node))
        if node is None or not node.alive:
            return
        changed = [(p.name, from_msg(p.value)) for p in list(msg.new_parameters) + list(msg.changed_parameters)]
        changed += [(p.name, None) for p in msg.deleted_parameters]
        self.gateway.spawn(self._observed(node, changed))

    async def _observed(self, node: "LiveNode", changed: list[tuple[str, Any]]) -> None:
        known = self.cache.get(node.key, {})
        expected = self.expected.get(node.key, {})
        now = time.monotonic()
        changes = []
        for name, value in changed:
            old = known.get(name, {}).get("value")
            if name in known:
                known[name] = {**known[name], "value": value}
            ours = expected.get(name)
            if ours is not None and ours[1] >= now and ours[0] == value:
                expected.pop(name)
                continue  # the echo of our own change, recorded already
            if old == value and name in known:
                continue
            changes.append({"name": name, "old": old, "new": value})
            await db(_record)(node, name, old, value, "succeeded", "", "external", None)
        if changes:
            log.info("parameters of %s:%s changed by another tool: %s", node.robot.name, node.name,
                     ", ".join(c["name"] for c in changes))
            await self._push(node, changes)

    async def _push(self, node: "LiveNode", changes: list[dict]) -> None:
        await self.gateway.relay.publish(
            [protocol.node_group(node.key)], {"type": "node.parameters", "node": node.key, "changes": changes}
        )

    def forget(self, node_key: str) -> None:
        self.cache.pop(node_key, None)
        self.expected.pop(node_key, None)


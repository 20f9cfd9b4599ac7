"""Parameters of managed nodes: listing, checked setting, and every change made by anyone
(seen on /parameter_events) recorded with its old and new value and pushed live."""
from __future__ import annotations

import logging
import time
from typing import Any, Callable

from ros_gateway.domain import RosDomain
from ros_gateway.lifecycle import NodeUnreachable
from ros_gateway.outbox import Outbox
from ros_gateway.parameters import (
    NoAnswer,
    from_msg,
    list_parameters,
    set_parameters,
    set_parameters_atomically,
    type_of,
)
from ros_gateway.registry import LiveNode, NodeRegistry, StateChange
from ros_gateway.relay import Relay
from ros_gateway.shared import param_types as pt
from ros_gateway.shared import protocol
from ros_gateway.tasks import spawn

log = logging.getLogger(__name__)

# How long a value we set waits for its /parameter_events echo before it counts as someone else's.
ECHO_WINDOW_S = 10.0


class ParameterKeeper:
    def __init__(self, domains: dict[int, RosDomain], registry: NodeRegistry, outbox: Outbox, relay: Relay,
                 timeout: float = 5.0) -> None:
        self.domains, self.registry, self.outbox, self.relay = domains, registry, outbox, relay
        self.timeout = timeout
        # node key -> {parameter name: listing entry}; filled on first use
        self.cache: dict[str, dict[str, dict]] = {}
        # node key -> what the cache held of a process since replaced by a new instance
        self.stale: dict[str, dict[str, dict]] = {}
        # node key -> {parameter name: (value we set, until when we expect its echo)}
        self.expected: dict[str, dict[str, tuple[Any, float]]] = {}

    async def listing(self, node: LiveNode, timeout: float) -> list[dict]:
        domain = self.domains[node.robot.domain_id]
        parameters = await list_parameters(domain, node.name, timeout)
        self.cache[node.key] = {p["name"]: p for p in parameters}
        return parameters

    def _record(self, node: LiveNode, name: str, old: Any, new: Any, outcome: str, reason: str, source: str,
                user_id: int | None, vouching: Callable[[str], dict] | None = None, run_id: str = "") -> dict:
        """Report one parameter change or refused attempt to the site (an audit fact; for a
        command of the site with its grant for that name, and the id that goes with it; for a
        step of a run, the run's id, by which the site knows who asked)."""
        return self.outbox.emit(protocol.PARAMETER, robot=node.robot.name, node=node.name, name=name,
                                old=protocol.bounded(old), new=protocol.bounded(new), outcome=outcome, reason=reason,
                                source=source, user_id=user_id, **(vouching(name) if vouching else {}),
                                **({"run_id": run_id} if run_id else {}))

    async def set(self, node: LiveNode, values: dict, timeout: float, source: str,
                  user_id: int | None, vouching: Callable[[str], dict] | None = None,
                  atomic: bool = False, run_id: str = "") -> tuple[list[dict], list[dict]]:
        """Check each value against the node's descriptors, send the good ones together, and
        record every outcome. Returns one result per requested name, in request order, and
        the audit facts reporting them. ``atomic``: all values or none (a parameter file): none
        is sent when one fails the checks, and the node sets them all or none."""
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
        if atomic and results and to_send:
            refused = ", ".join(results)
            for name in to_send:
                results[name] = {"successful": False,
                                 "reason": f"not sent: {refused} could not be set, and these values go all or none"}
            to_send = {}
        if to_send:
            until = time.monotonic() + ECHO_WINDOW_S
            self.expected.setdefault(node.key, {}).update({n: (v, until) for n, (v, _) in to_send.items()})
            domain = self.domains[node.robot.domain_id]
            try:
                send = set_parameters_atomically if atomic else set_parameters
                answers = await send(domain, node.name, to_send, timeout)
            except NoAnswer as exc:
                # Sent, but no answer: the node may have taken the values. Said so, and recorded.
                answers = [{"name": name, "successful": False, "unknown": True,
                            "reason": f"no answer from the node ({exc}); the value may or may not be set"}
                           for name in to_send]
            for answer in answers:
                name = answer["name"]
                results[name] = {"successful": answer["successful"],
                                 "reason": answer["reason"] or ("" if answer["successful"] else "refused by the node")}
                if answer.get("unknown"):
                    results[name]["outcome"] = "timed_out"
                elif not answer["successful"]:
                    self.expected.get(node.key, {}).pop(name, None)
        ordered = []
        facts: list[dict] = []
        changes = []
        for name, value in values.items():
            result = results[name]
            old = olds[name]
            new = to_send[name][0] if name in to_send else value
            if result["successful"]:
                known[name] = {**known[name], "value": new}
                changes.append({"name": name, "old": old, "new": new})
            outcome = result.pop("outcome", "succeeded" if result["successful"] else "rejected")
            facts.append(self._record(node, name, old, new, outcome, result["reason"], source, user_id, vouching,
                                      run_id))
            ordered.append({"name": name, "old": old, "new": new, **result})
        if changes:
            self._push(node, changes)
        return ordered, facts

    def on_event(self, domain_id: int, msg) -> None:
        """/parameter_events of one domain (on the gateway loop)."""
        node = self.registry.nodes.get((domain_id, msg.node))
        if node is None or not node.alive:
            return
        # A new parameter of a node whose listing was never read (or was dropped with its old
        # process) is the node declaring it as it starts, not a change made by anyone; once the
        # listing is known, a new name is a value set on an undeclared parameter.
        declared = list(msg.new_parameters) if node.key in self.cache else []
        changed = [(p.name, from_msg(p.value)) for p in declared + list(msg.changed_parameters)]
        changed += [(p.name, None) for p in msg.deleted_parameters]
        self._observed(node, changed)

    def _observed(self, node: LiveNode, changed: list[tuple[str, Any]]) -> None:
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
            self._record(node, name, old, value, "succeeded", "", "external", None)
        if changes:
            log.info("parameters of %s:%s changed by another tool: %s", node.robot.name, node.name,
                     ", ".join(c["name"] for c in changes))
            self._push(node, changes)

    def _push(self, node: LiveNode, changes: list[dict]) -> None:
        spawn(self.relay.publish({"type": "node.parameters", "robot": node.robot.name, "name": node.name,
                                  "node": node.key, "changes": changes}))

    def forget(self, node_key: str) -> None:
        """The node may be a new process: what we knew of its parameters is the old one's."""
        self.expected.pop(node_key, None)
        if node_key in self.cache:
            self.stale[node_key] = self.cache.pop(node_key)

    def on_change(self, change: StateChange) -> None:
        """State-change listener: a new instance of a node's process whose old parameters were
        shown has them read again, so that open pages show the new process's values."""
        if change.kind == "state" and change.respawned and change.node.key in self.stale:
            spawn(self.reread(change.node))

    async def reread(self, node: LiveNode) -> None:
        old = self.stale.pop(node.key, None)
        if old is None:
            return
        try:
            fresh = await self.listing(node, self.timeout)
        except NodeUnreachable as exc:
            log.info("could not read the parameters of the new instance of %s on %s: %s",
                     node.name, node.robot.name, exc)
            return
        changes = [{"name": p["name"], "old": old.get(p["name"], {}).get("value"), "new": p["value"]}
                   for p in fresh if old.get(p["name"], {}).get("value") != p["value"]]
        if changes:
            log.info("new instance of %s on %s: parameters now %s", node.name, node.robot.name,
                     ", ".join(f"{c['name']}={c['new']!r}" for c in changes))
            self._push(node, changes)


"""Playing a gateway's part against the real Redis, exactly as the wire contract says (facts and
log batches XADDed, heartbeat SET, commands BRPOPped and answered), for site tests that run
without a gateway process."""
from __future__ import annotations

import json
from datetime import datetime, timedelta, timezone

from lifecycle_site.gateway_link import attribution
from lifecycle_site.gateway_link.gateways import channel_prefix
from ros_gateway.shared import protocol
from tests import stack


def iso(moment: datetime | None = None) -> str:
    return (moment or datetime.now(timezone.utc)).isoformat()


class GatewayPart:
    """One gateway process (one ``instance``): its facts get sequence numbers 1, 2, 3 ..."""

    def __init__(self, name: str, instance: str | None = None) -> None:
        self.name = name
        self.instance = instance or protocol.new_id()
        self.seq = 0
        self.log_seq = 0
        self.redis = stack.redis_client()
        self.prefix = channel_prefix()
        self.clock = datetime.now(timezone.utc)

    def tick(self) -> str:
        """A strictly later time for each fact (as a gateway's clock gives)."""
        self.clock += timedelta(milliseconds=1)
        return iso(self.clock)

    def fact(self, kind: str, **fields) -> dict:
        self.seq += 1
        return {"id": protocol.new_id(), "type": kind, "gateway": self.name, "instance": self.instance,
                "seq": self.seq, "at": self.tick(), **fields}

    def emit(self, *facts: dict) -> list[dict]:
        with self.redis.pipeline(transaction=False) as pipe:
            for fact in facts:
                pipe.xadd(protocol.facts_stream(self.prefix, self.name), {"f": protocol.encode(fact)},
                          maxlen=protocol.FACTS_MAXLEN, approximate=True)
            pipe.execute()
        return list(facts)

    def transition(self, robot: str, node: str, transition_id: int, label: str, start: int, result: int,
                   outcome: str = "succeeded", **extra) -> dict:
        """A transition's audit fact; one of the site's sources (api, dashboard, cli) comes with
        the site's grant, as a gateway answering the site's command sends it."""
        now = self.tick()
        fact = self.fact(protocol.TRANSITION, robot=robot, node=node, transition_id=transition_id,
                         transition_label=label, start_state=start, result_state=result, outcome=outcome,
                         source=extra.pop("source", "api"), user_id=extra.pop("user_id", None), requested_at=now,
                         completed_at=now, error=extra.pop("error", ""), run_id=extra.pop("run_id", ""), **extra)
        return fact if fact["source"] in attribution.GATEWAY_SOURCES or fact["run_id"] else self.vouch(fact)

    @staticmethod
    def vouch(fact: dict) -> dict:
        """The fact with the grant the site gave the command it answers, and the id that goes
        with it (lifecycle_site/gateway_link/attribution.py, protocol.vouching)."""
        request_id = fact["request_id"] = fact["id"]
        node = fact.get("node")
        if fact["type"] == protocol.TRANSITION:
            what = f"transition:{fact['transition_label']}"
        elif fact["type"] == protocol.PROCESS:
            what, node = f"process:{fact['action']}", fact.get("process")
        else:
            what = f"parameter:{fact['name']}"
            fact["id"] = protocol.parameter_fact_id(request_id, fact["name"])
        fact["grant"] = attribution.grant(request_id, fact.get("user_id"), fact.get("source"), fact.get("robot"),
                                          node, what)
        return fact

    def log_batch(self, records: list[list], dropped: int = 0) -> dict:
        self.log_seq += 1
        batch = {"id": protocol.new_id(), "gateway": self.name, "instance": self.instance, "seq": self.log_seq,
                 "dropped": dropped, "records": records}
        self.redis.xadd(protocol.logs_stream(self.prefix, self.name), {"f": protocol.encode(batch)},
                        maxlen=protocol.LOGS_MAXLEN, approximate=True)
        return batch

    def beat(self, **fields) -> dict:
        return stack.write_beat(self.name, instance=self.instance, **fields)

    def queue_length(self) -> int:
        return self.redis.llen(protocol.command_queue(self.prefix, self.name))

    def take_command(self, timeout: float = 10) -> dict | None:
        popped = self.redis.brpop([protocol.command_queue(self.prefix, self.name)], timeout=timeout)
        return json.loads(popped[1]) if popped else None

    def reply(self, command: dict, **payload) -> None:
        key = protocol.reply_key(self.prefix, self.name, command["request_id"])
        self.redis.lpush(key, protocol.encode({"request_id": command["request_id"], **payload}))
        self.redis.expire(key, protocol.REPLY_TTL_S)


def clear_streams(name: str) -> None:
    """Forget a gateway's keys (tests reuse names across a run's Redis)."""
    client = stack.redis_client()
    keys = list(client.scan_iter(match=protocol.gateway_keys_pattern(channel_prefix(), name)))
    if keys:
        client.delete(*keys)


def forget_ingest_processes() -> None:
    """Drop every ingest process's leases and turns (a test's Ingest objects are not stopped)."""
    client = stack.redis_client()
    keys = list(client.scan_iter(match=f"{channel_prefix()}:site:ingest:*")) + [f"{channel_prefix()}:site:quarantined"]
    client.delete(*keys)

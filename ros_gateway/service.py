"""The gateway worker: an agent beside its robots that dials out to the site over Redis and
never opens the site's database.

This module only puts the parts together and runs their loops; each part gets what it
uses. One asyncio loop owns all bookkeeping; each watched ROS domain has its own rclpy
Context and executor threads (domain.py). Any single failure is logged and the loop goes on.

    relay.py      Redis: commands in, replies out, heartbeat, lease, the site's config
    outbox.py     facts out (durable, bounded), numbered for the site's ingest process
    registry.py   robots and live nodes; the one stream of state changes
    discovery.py  domains, nodes appearing and vanishing, states kept current
    lifecycle.py  one checked transition, audited      groups.py   group runs, recovery
    param_keeper.py  parameters                        logs.py     /rosout to the site
    commands.py   the site's requests
"""
from __future__ import annotations

import asyncio
import logging
import os
import socket
from datetime import datetime, timezone
from typing import Callable

from ros_gateway import budget, leftovers, tasks, topic_rates
from ros_gateway.commands import CommandHandler, Parts
from ros_gateway.config import GatewayConfig
from ros_gateway.desired_keeper import DesiredKeeper
from ros_gateway.diagnostics import Diagnostics
from ros_gateway.discovery import Discovery
from ros_gateway.domain import RosDomain
from ros_gateway.groups import GroupRunner
from ros_gateway.host_units import DockerEngine, HostUnits, Systemd
from ros_gateway.launch_profile import LaunchProfile
from ros_gateway.liveness import Liveness
from ros_gateway.logs import LogPipeline
from ros_gateway.node_driver import NodeDriver
from ros_gateway.outbox import Outbox
from ros_gateway.param_keeper import ParameterKeeper
from ros_gateway.parts import Core
from ros_gateway.process_owners import ProcessOwners
from ros_gateway.process_usage import ProcessUsage
from ros_gateway.recovery import Recovery
from ros_gateway.registry import NodeRegistry, StateChange, StateChanges
from ros_gateway.relay import Relay
from ros_gateway.shared import protocol
from ros_gateway.supervisor import Supervisor
from ros_gateway.topic_rates import TopicRates

log = logging.getLogger(__name__)

VERSION = "2.0"
# How often all live nodes' "last seen" goes to the site, and all states are re-read.
RESYNC_EVERY_S = 30.0
# How often nodes are matched to the supervised processes that run them (cheap: only what changed).
OWNERS_EVERY_S = 2.0
# A stopping gateway's last words to Redis, each bounded: a supervisor (docker stop: 10 s)
# would kill a gateway that waited out every Redis call's timeout and retries (over a minute).
STOP_FLUSH_S = 4.0
STOP_FAREWELL_S = 2.0


class AlreadyRunning(RuntimeError):
    """Another live process holds this gateway's lease."""


class Gateway:
    def __init__(self, config: GatewayConfig) -> None:
        self.config = config
        self.instance = protocol.new_id()
        self.started = datetime.now(timezone.utc)
        self._stopping = asyncio.Event()
        self.relay = Relay(config.name, config.redis_url, config.prefix, instance=self.instance)
        self.outbox = Outbox(self.relay, config.name, self.instance)
        self.changes = StateChanges(report=self._report)
        self.registry = NodeRegistry(self.changes)
        self.domains: dict[int, RosDomain] = {}
        self.logs = LogPipeline(self.registry, self.outbox, config.log_buffer)
        self.params = ParameterKeeper(self.domains, self.registry, self.outbox, self.relay, config.service_timeout)
        core = Core(self.registry, self.domains, self.outbox, self.relay, config.service_timeout)
        self.processes = core.processes
        self.liveness = Liveness(self.registry, self.domains, config.liveness_interval, config.liveness_timeout,
                                 local=self._of_this_host)
        self.discovery = Discovery(core, self._new_domain, self.params.forget, self.liveness.holds_back,
                                   self.liveness.suspect)
        self.driver = NodeDriver(core, self.logs)
        self.runs = GroupRunner(core, self.driver, self.params)
        self.recovery = Recovery(self.runs)
        self.keeper = DesiredKeeper(self.runs, self.registry, self.discovery.read_state)  # kept against other tools
        self.rates = TopicRates(self.registry, self.domains, self.outbox)  # for the modes' readiness
        self.diagnostics = Diagnostics(self.registry, self.domains, self.outbox)  # the robots' /diagnostics
        self.discovery.on_external = self.keeper.on_external
        # The robots' launch profiles: processes this gateway runs for them (its facts: audit records).
        self.owner = leftovers.owner(config.name, config.redis_url, config.prefix)  # (its processes' mark)
        self.supervisor = Supervisor(self._report_process, self.logs.on_output, self.owner, self.discovery.hurry)
        # Containers and systemd units of this host that run robots' nodes, and their supervisors.
        self.units = HostUnits(self._report_process, DockerEngine(config.docker_socket), Systemd(config.systemd),
                               on_launch=self.discovery.hurry)
        self.owners = ProcessOwners(self.registry, self.processes, self.supervisor.pids, self._report_owner,
                                    self.units)
        self.commands = CommandHandler(Parts(core, self.driver, self.params, self.runs, self.supervisor, self.units,
                                             self.recovery, ProcessUsage()))
        # A state change is reported to the site first (self._report, its fact kept on the change);
        # then, in this order: the pages (a push), the audit of a new process instance, its
        # parameters read again, the stuck-transition check, and automatic recovery.
        self.changes.subscribe("push", self._push)
        self.changes.subscribe("restarts", self.discovery.records.on_change)
        self.changes.subscribe("parameters", self.params.on_change)
        self.changes.subscribe("settle", self.discovery.on_change)
        self.changes.subscribe("recover", self.recovery.on_change)

    def _new_domain(self, domain_id: int) -> RosDomain:
        return RosDomain(domain_id, asyncio.get_running_loop(), self.discovery.on_transition_event,
                         self.logs.on_log, self.params.on_event)

    # -- state-change listeners --------------------------------------------------------
    def _report(self, change: StateChange) -> dict:
        """The change's fact for the site, emitted and returned."""
        node = change.node
        kind = {"seen": protocol.NODE_SEEN, "gone": protocol.NODE_GONE, "state": protocol.NODE_STATE}[change.kind]
        fields = {"state_id": change.state_id} if change.kind == "state" else {}
        if change.reason:
            fields["reason"] = change.reason
        if change.reason == protocol.PROCESS_LOST and node.process_since is not None:
            fields["since"] = node.process_since.isoformat()  # the time the node's payload shows
        return self.outbox.emit(kind, robot=node.robot.name, node=node.name, **fields)

    def _report_process(self, **fields) -> dict:
        """A process's audit fact (a launch profile's, a container's or a unit's), emitted and returned."""
        return self.outbox.emit(protocol.PROCESS, **fields)

    def _report_owner(self, node) -> None:
        self.outbox.emit(protocol.NODE_PROCESS, robot=node.robot.name, node=node.name, process=node.process)

    def _push(self, change: StateChange) -> None:
        """The node's live update, after its previous one (so pages see them in order)."""
        node, previous = change.node, change.node.last_push
        message = {"type": "node.state", "node": node.payload()}

        async def send() -> None:
            if previous is not None and not previous.done():
                await asyncio.gather(previous, return_exceptions=True)
            await self.relay.publish(message)

        node.last_push = tasks.spawn(send())

    async def _end_leftovers(self) -> None:
        """End what a killed predecessor's launch profiles left running (leftovers.py), each on record."""
        for found, pids in (await leftovers.end(self.owner)).items():
            _, robot, name = found.split("/", 2) if found.count("/") >= 2 else ("", "", found)
            log.warning("ended %d process(es) of %s on %s left running by this gateway's previous instance: %s",
                        len(pids), name, robot, pids)
            self.outbox.emit(protocol.PROCESS, robot=robot, process=name, supervisor="launch", action="stop",
                             outcome="succeeded", source="supervisor", user_id=None, pid=None, old_pid=pids[0],
                             exit_code=None, exit_signal=None, took_ms=None,
                             message=f"{name} on {robot}: {len(pids)} process(es) left running by the gateway's "
                                     f"previous instance (it was killed) ended: pid {', '.join(map(str, pids))}.")

    def _of_this_host(self, domain_id: int, participant: bytes) -> bool:
        """Whether the participant is a running process of this host (its end is then seen in /proc
        by discovery). A stopped one is not: liveness probes it at every pass, as a remote one."""
        found = self.processes.process(domain_id, participant)
        return found is not None and not self.processes.stopped(found)

    async def _refresh_owners(self) -> None:
        await self.owners.refresh()

    # -- running ----------------------------------------------------------------------
    async def run(self) -> None:
        config = self.config
        await self._take_lease()
        self.outbox.emit(protocol.GATEWAY_STARTED)
        await self._end_leftovers()
        loops = [
            self.outbox.run(self._stopping),
            self._every(config.robot_refresh_interval, self.refresh_robots, "robot refresh"),
            self._every(lambda: self.discovery.pause(config.discovery_interval), self.discovery.discover,
                        "discovery"),
            self._every(config.heartbeat_interval, self.heartbeat, "heartbeat"),
            self._every(RESYNC_EVERY_S, self.discovery.resync_states, "state resync"),
            self._every(OWNERS_EVERY_S, self._refresh_owners, "process owners"),
            self._every(topic_rates.REPORT_S, self.rates.report, "topic rates"),
            *([self._every(config.liveness_interval, self.liveness.probe, "liveness probe")]
              if self.liveness.enabled else []),
            self.logs.run(self._stopping),
            self.commands.run(self._stopping),
            self.diagnostics.run(self._stopping),
        ]
        await self.refresh_robots()  # robots watched before the site hears this gateway is online
        await self.heartbeat()
        log.info("ROS gateway %r running (instance %s, Redis at %s)", config.name, self.instance, self.relay.url)
        running = [asyncio.create_task(c) for c in loops]
        await self._stopping.wait()
        for task in running:
            task.cancel()
        await asyncio.gather(*running, return_exceptions=True)
        try:  # the processes it runs end with it (as ros2 launch's do); the next instance starts them
            await self.supervisor.close()
        except Exception:
            log.exception("stopping the supervised processes failed")
        await tasks.cancel_all()
        self.logs.collect()
        try:  # what is still held goes out if Redis answers; bounded, the process is stopping
            await asyncio.wait_for(self.outbox.flush(), STOP_FLUSH_S)
        except Exception:
            log.warning("stopping with %s facts and log batches not sent", self.outbox.counters())
        for domain in list(self.domains.values()):
            await asyncio.to_thread(domain.stop)
        try:  # bounded too: each Redis call would otherwise wait out its timeout and retries
            await asyncio.wait_for(self._farewell(), STOP_FAREWELL_S)
        except Exception as exc:
            log.warning("stopping without a last word to Redis (%s): the site calls this gateway offline once "
                        "its beats stop, and its lease runs out by itself within %g s",
                        "no answer within %g s" % STOP_FAREWELL_S if isinstance(exc, asyncio.TimeoutError) else exc,
                        self.config.lease_ttl)

    async def _farewell(self) -> None:
        """The last beat (the site calls the gateway offline at once) and the lease given back."""
        await self.relay.beat({**self._beat(), "stopped": True})
        await self.relay.release_lease(self.instance)
        await self.relay.close()

    def stop(self) -> None:
        self._stopping.set()

    async def _every(self, interval: float | Callable[[], float], job, what: str) -> None:
        """``job`` again and again, ``interval`` seconds (or what it returns, asked each time) apart."""
        def pause() -> float:
            return interval() if callable(interval) else interval

        while not self._stopping.is_set():
            try:
                await job()
            except Exception:
                log.exception("%s failed; trying again in %.1f s", what, pause())
            try:
                await asyncio.wait_for(self._stopping.wait(), pause())
            except asyncio.TimeoutError:
                pass

    async def _take_lease(self) -> None:
        """Only one process acts as this gateway. A predecessor on this host whose process has
        ended (killed, say) is replaced at once (lease.py); elsewhere its lease runs out within
        its time-to-live, so a respawned gateway waits for it rather than failing."""
        ttl = self.config.lease_ttl
        deadline = asyncio.get_running_loop().time() + 2 * ttl + 1
        while True:
            try:
                holder = await self.relay.take_lease(self.instance, ttl)
            except Exception as exc:
                self.relay.complain("taking this gateway's lease", exc)
                holder = "unknown (Redis unreachable)"
                deadline += 1.0  # Redis down: keep waiting for it, do not give up on the lease
            if holder is None:
                return
            if asyncio.get_running_loop().time() > deadline:
                raise AlreadyRunning(
                    f"A gateway named {self.config.name!r} is already running (its lease is held by {holder} and "
                    "kept renewed). Stop it, or start this one under another name."
                )
            await asyncio.sleep(0.5)

    # -- housekeeping ---------------------------------------------------------------------
    async def refresh_robots(self) -> None:
        config = await self.relay.read_config()
        if config is not None:
            quota = budget.quota_of(config)
            if quota is not None:
                self.outbox.set_quota(quota)
                self.relay.live.set_quota(quota)
            await self.discovery.apply_config(config)
            self.keeper.on_settings()
            self.rates.apply(config)
            self.diagnostics.apply(config)
            await self.supervisor.apply(self._profiles(config))

    def _profiles(self, config: dict) -> list[LaunchProfile]:
        """The launch profiles of the watched robots in the site's config; one the gateway cannot
        read is left out (and said so once per config)."""
        profiles = []
        for robot in config.get("robots") or []:
            if not isinstance(robot, dict) or self.registry.robot_named(str(robot.get("name"))) is None:
                continue
            for data in robot.get("processes") or []:
                try:
                    profiles.append(LaunchProfile.from_config(str(robot["name"]), data))
                except ValueError as exc:
                    if config.get("version") != self._complained_about:
                        log.error("ignored a launch profile of robot %s: %s", robot.get("name"), exc)
        self._complained_about = config.get("version")
        return profiles

    _complained_about: object = None

    def _beat(self) -> dict:
        return {
            "name": self.config.name,
            "instance": self.instance,
            "version": VERSION,
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "started": self.started.isoformat(),
            "at": datetime.now(timezone.utc).timestamp(),
            "interval": self.config.heartbeat_interval,
            "domains": sorted(self.domains),
            "dds": self.config.dds,
            "robots": len(self.registry.robots),
            "nodes": self.registry.alive_count(),
            "unreachable_processes": len(self.liveness.unreachable),
            "outbox": self.outbox.counters(),
            "client": self.relay.client_name,
            "stopped": False,
        }

    async def heartbeat(self) -> None:
        if not await self.relay.renew_lease(self.instance, self.config.lease_ttl):
            log.error("another process took over gateway %r (this one was frozen or cut off longer than its "
                      "lease); stopping", self.config.name)
            self.stop()
            return
        await self.relay.beat(self._beat())

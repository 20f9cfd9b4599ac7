"""``manage.py lifecycle VERB ...``: ``ros2 lifecycle`` against the site, through the gateway.

``manage.py lifecycle --help`` describes the verbs, the node names and the exit statuses. Its
human output is in German or English: languages/cli.py ($LIFECYCLE_LANGUAGE, else $LANG).
"""
from __future__ import annotations

import getpass
import os
import sys
from types import SimpleNamespace
from typing import Any

from django.contrib.auth import get_user_model
from django.core.management.base import BaseCommand, CommandError
from django.db import DatabaseError
from django.db.models import Q
from django.utils import timezone, translation
from django.utils.translation import gettext as _

from lifecycle_site.diagnostics import tree
from lifecycle_site.diagnostics.models import Status
from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from lifecycle_site.gateway_link.gateway_client import GatewayError, GatewayOffline, call_gateway
from lifecycle_site.languages.cli import InCliLanguage, cli_language
from lifecycle_site.modes import drift
from lifecycle_site.operations import cli_output as out
from lifecycle_site.operations import modes, processes
from lifecycle_site.operations.runs import start_run, wait_for
from lifecycle_site.operations.transitions import TransitionRefused, ago, named, request_transition
from lifecycle_site.refusal import Refusal
from ros_gateway.shared import operations, protocol
from ros_gateway.shared import state_machine as sm

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_OFFLINE, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


class CliExit(CommandError):
    """End the command with ``returncode``; ``message`` goes to stderr (and as JSON with --json)."""

    def __init__(self, returncode: int, message: str = "", code: str | None = None, **details: Any) -> None:
        super().__init__(message, returncode=returncode)
        self.message, self.code, self.details = message, code, details


class Command(InCliLanguage, BaseCommand):
    help = out.DESCRIPTION
    requires_system_checks: list[str] = []  # a quick CLI: the site and the gateway run the checks

    def create_parser(self, prog_name: str, subcommand: str, **kwargs: Any):
        parser = super().create_parser(prog_name, subcommand, formatter_class=out.HelpFormatter, **kwargs)
        parser.epilog = str(out.EPILOG)
        return parser

    def add_arguments(self, parser) -> None:
        out.add_verbs(parser)

    def execute(self, *args: Any, **options: Any) -> None:
        # The CLI's language for all of it: handle() and the error written here after it.
        with translation.override(cli_language()):
            self._execute(*args, **options)

    def _execute(self, *args: Any, **options: Any) -> None:
        try:
            super().execute(*args, **options)
            return
        except CliExit as exc:
            error = exc
        except (GatewayOffline, DatabaseError, KeyboardInterrupt) as exc:
            if options.get("traceback"):
                raise
            error = as_exit(exc)
        if error.message:
            if options.get("json") and error.code:
                body = {"error": {"code": error.code, "message": error.message, **error.details}}
                self.stdout.write(out.to_json(body))
            self.stderr.write(error.message)
        if getattr(self, "_called_from_command_line", False):  # set by run_from_argv (not by call_command)
            sys.exit(error.returncode)  # Django would print the message again, after "CommandError: "
        raise error

    def handle(self, *args: Any, verb: str, **options: Any) -> None:
        opts = SimpleNamespace(verb=verb, **options)
        handlers = {"nodes": self.do_nodes, "get": self.do_get, "set": self.do_set, "list": self.do_list,
                    "process": self.do_process, "mode": self.do_mode, "diagnostics": self.do_diagnostics}
        code = handlers.get(verb, self.do_group)(opts)
        if code:
            raise CliExit(code)

    def emit(self, opts: SimpleNamespace, data: Any, lines: list[str]) -> None:
        self.stdout.write(out.to_json(data) if opts.json else "\n".join(lines))

    # --- read-only verbs -------------------------------------------------------------------

    def do_nodes(self, opts: SimpleNamespace) -> int:
        robot = self.robot(opts.robot)
        listed = self.listed(robot, opts.all)
        if opts.count_nodes:
            self.emit(opts, {"count": len(listed)}, [str(len(listed))])
        else:
            lines = [out.node_label(n, robot is None) + out.lost_mark(n) for n in listed]
            self.emit(opts, {"nodes": [out.node_json(n) for n in listed]}, lines)
        return EXIT_OK

    def do_get(self, opts: SimpleNamespace) -> int:
        robot = self.robot(opts.robot)
        if opts.node:
            node = self.node(opts.node, robot)
            state, live = self.read_states([node], opts.timeout)[0]
            self.emit(opts, out.node_json(node, state, live=live), [out.state_text(state)])
            return EXIT_OK
        listed = self.listed(robot, opts.all)
        readings = list(zip(listed, self.read_states(listed, opts.timeout), strict=True))
        lines = [f"{out.node_label(n, robot is None)}: {out.state_text(s)}{out.lost_mark(n)}" for n, (s, _) in readings]
        self.emit(opts, {"nodes": [out.node_json(n, s, live=live) for n, (s, live) in readings]}, lines)
        return EXIT_OK

    def read_states(self, nodes: list[ManagedNode], timeout: float | None) -> list[tuple[dict, bool]]:
        """Each node's live state from the gateway, else its last known state (noted on stderr)."""
        readings: list[tuple[dict, bool]] = []
        offline: set[str] = set()  # gateways found offline: their other nodes are not asked
        for node in nodes:
            gateway = node.robot.gateway.name
            if node.alive and gateway not in offline:
                try:
                    reply = call_gateway(gateway, protocol.GET_STATE, timeout=timeout, robot=node.robot.name,
                                         node=node.name)
                    state = reply.get("state") if isinstance(reply.get("state"), dict) else {}
                    found = state.get("id") if state.get("id") in sm.STATE_LABELS else sm.UNKNOWN
                    readings.append((sm.state_dict(found), True))
                    continue
                except GatewayOffline as exc:
                    offline.add(gateway)
                    self.stderr.write(_("%(reason)s Showing the last known state instead.") % {"reason": exc.message})
                except GatewayError as exc:
                    self.stderr.write(_("%(node)s: %(reason)s Showing its last known state.") % {
                        "node": node.key, "reason": exc.message})
            elif not node.alive and len(nodes) == 1:
                self.stderr.write(_("%(node)s is not running (last seen %(ago)s); showing its last known state.") % {
                    "node": node.key, "ago": ago(node.last_seen)})
            readings.append((node.state, False))
        return readings

    def do_list(self, opts: SimpleNamespace) -> int:
        node = self.node(opts.node, self.robot(opts.robot))
        command, field = (protocol.GET_TRANSITION_GRAPH, "graph") if opts.all else (
            protocol.GET_AVAILABLE_TRANSITIONS, "transitions")
        try:
            reply = call_gateway(node.robot.gateway.name, command, timeout=opts.timeout, robot=node.robot.name,
                                 node=node.name)
        except GatewayOffline:
            raise
        except GatewayError as exc:
            raise CliExit(EXIT_FAILED, f"{node.key}: {exc.message}", exc.code) from None
        key = "transition_graph" if opts.all else "transitions"
        self.emit(opts, {"node": node.key, key: reply[field]}, out.transition_lines(reply[field]))
        return EXIT_OK

    # --- changing verbs --------------------------------------------------------------------

    def do_set(self, opts: SimpleNamespace) -> int:
        node = self.node(opts.node, self.robot(opts.robot))
        requested = self.transition(opts.transition)
        try:
            done = request_transition(node, requested, self.user(opts.user), "cli", opts.timeout)
        except TransitionRefused as refused:
            if refused.code == "gateway_offline":
                raise CliExit(EXIT_OFFLINE, refused.message, refused.code, **refused.details) from None
            self.emit(opts, refused.as_json(), [_("Transitioning failed")])
            self.stderr.write(refused.message)
            if refused.code == "invalid_transition" and not opts.json:
                state_id = refused.details["state"]["id"]
                self.stderr.write("\n".join(out.available_lines(state_id, refused.details.get("valid_transitions"))))
            return EXIT_FAILED
        self.emit(opts, done.data, [_("Transitioning successful")])
        return EXIT_OK

    def do_process(self, opts: SimpleNamespace) -> int:
        """A robot's supervised processes, or one action on one of them."""
        robot = self.robot(opts.robot_name)
        if not opts.process:
            found = processes.robot_processes(robot)
            measured = processes.usage(robot, {p.name for p in found}) if found else {}
            lines = [out.process_line(p, measured.get(p.name)) for p in found] or [
                _("%(robot)s has no launch profiles, and its gateway has found none of its nodes in a container or "
                  "systemd unit it can reach.") % {"robot": robot.name}]
            self.emit(opts, {"robot": robot.name, "processes": [{**p.as_dict(), "usage": measured.get(p.name)}
                                                                for p in found]}, lines)
            return EXIT_OK
        if not opts.action:
            raise CliExit(EXIT_USAGE, _("What should happen to %(process)s? Give an action: %(actions)s.") % {
                "process": opts.process, "actions": ", ".join(protocol.PROCESS_ACTIONS)})
        try:
            profile = processes.profile_of(robot, opts.process)
        except Refusal as exc:
            raise CliExit(EXIT_USAGE, exc.message, exc.code) from None
        try:
            record = processes.control(profile, opts.action, self.user(opts.user), "cli")
        except Refusal as refused:
            if refused.code == "gateway_offline":
                raise CliExit(EXIT_OFFLINE, refused.message, refused.code, **refused.details) from None
            self.emit(opts, refused.as_json(), [_("%(action)s failed") % {"action": opts.action}])
            self.stderr.write(refused.message)
            return EXIT_FAILED
        self.emit(opts, {"record": record.as_dict()}, [record.message])
        return EXIT_OK

    def do_group(self, opts: SimpleNamespace) -> int:
        """An operation of the shared table, of a robot or of a node: one GroupRun."""
        operation = operations.BY_NAME[opts.verb]
        if operation.scope == operations.NODE:
            node = self.node(opts.node, self.robot(opts.robot))
            robot, only = node.robot, [node.name]
        else:
            robot, only = self.robot(self.robot_name(opts)), None
        user = self.user(opts.user)
        extra = {"node_timeout": opts.timeout} if opts.timeout else {}
        try:
            run = start_run(robot, opts.verb, user=user, source="cli", policy=opts.policy, nodes=only, **extra)
        except Refusal as exc:
            raise refused_exit(exc) from None
        return self.follow(opts, run, operation)

    def do_mode(self, opts: SimpleNamespace) -> int:
        """A robot's modes: list, show one, apply one (a run, followed as the operations are), drift."""
        robot = self.robot(opts.robot_name)
        summary = drift.summary(robot)
        if opts.action == "list":
            found = [m.as_dict() for m in robot.modes.prefetch_related("robots")]
            self.emit(opts, {"robot": robot.name, **summary, "modes": found},
                      out.mode_lines(found, summary["mode"], summary.get("since")))
            return EXIT_OK
        if opts.action == "drift":
            lines = [d["message"] for d in summary["drift"]] or (
                [_("%(robot)s is in mode %(mode)s") % {"robot": robot.name, "mode": summary["mode"]}]
                if summary["mode"] else [_("%(robot)s has no mode") % {"robot": robot.name}])
            self.emit(opts, {"robot": robot.name, **summary}, lines)
            return EXIT_FAILED if summary["drift"] else EXIT_OK
        if not opts.mode:
            raise CliExit(EXIT_USAGE, _("Which mode? Give MODE after the robot (%(action)s ROBOT MODE).") % {
                "action": opts.action})
        try:
            mode = modes.mode_of(robot, opts.mode)
            if opts.action == "show":
                self.emit(opts, {"mode": mode.as_dict()}, out.mode_node_lines(mode.as_dict()))
                return EXIT_OK
            extra = {"node_timeout": opts.timeout} if opts.timeout else {}
            run = modes.apply_mode(robot, mode, user=self.user(opts.user), source="cli", policy=opts.policy, **extra)
        except Refusal as exc:
            raise refused_exit(exc) from None
        return self.follow(opts, run, modes.MODE_RUN)

    def do_diagnostics(self, opts: SimpleNamespace) -> int:
        """A robot's diagnostic statuses as a tree; exit 1 while one is in ERROR or stale."""
        robot = self.robot(opts.robot_name)
        statuses = list(Status.objects.filter(robot=robot))
        branches = tree.rows(tree.build(statuses))
        if opts.problems:
            branches = [b for b in branches if b.word != "OK"]
        rows = tree.as_dicts(branches)
        counts = tree.counts(statuses)
        self.emit(opts, {"robot": robot.name, "counts": counts, "tree": rows},
                  out.diagnostic_lines(rows, robot.name, timezone.now(), len(statuses)))
        return EXIT_FAILED if counts["ERROR"] or counts["STALE"] else EXIT_OK

    def follow(self, opts: SimpleNamespace, run: GroupRun, operation: operations.Operation) -> int:
        """Print the run's nodes as they are done, then its summary; its exit status."""
        shown: set[str] = set()

        def progress(current: GroupRun) -> None:
            """Print each node's line as its result arrives (the gateway adds a node once done;
            nodes driven side by side may finish in any order). A node of an operation in
            phases is done only when the run is (its line would be of its first phase)."""
            if len(operation.phases) > 1 and not current.done:
                return
            for result in current.results:
                if result["node"] not in shown:
                    shown.add(result["node"])
                    self.stdout.write(out.result_line(result))

        try:
            run = wait_for(run, opts.wait, None if opts.json else progress)
        except KeyboardInterrupt:
            raise CliExit(EXIT_INTERRUPTED, _("Interrupted: stopped following run %(run)s; it goes on in the "
                                              "gateway.") % {"run": run.id}) from None
        if opts.json:
            self.stdout.write(out.to_json({"run": run.as_dict()}))
        else:
            progress(run)
            self.stdout.write(out.summary_line(run))
        if not run.done:
            self.stderr.write(_("Run %(run)s was still %(status)s after %(seconds)s s; it goes on in the gateway.") % {
                "run": run.id, "status": run.get_status_display(), "seconds": f"{opts.wait:g}"})
        return EXIT_OK if run.status == GroupRun.Status.SUCCEEDED else EXIT_FAILED

    # --- what the arguments name -----------------------------------------------------------

    def robot(self, name: str | None) -> Robot | None:
        if not name:
            return None
        robot = Robot.objects.select_related("gateway").filter(name=name).first()
        if robot is None:
            known = list(Robot.objects.values_list("name", flat=True))
            raise CliExit(EXIT_USAGE, out.unknown_robot(name, known), "not_found")
        return robot

    def robot_name(self, opts: SimpleNamespace) -> str:
        if opts.robot_name and opts.robot and opts.robot_name != opts.robot:
            raise CliExit(EXIT_USAGE, _("ROBOT %(robot)s and --robot %(option)s differ; give one.") % {
                "robot": repr(opts.robot_name), "option": repr(opts.robot)})
        if not (opts.robot_name or opts.robot):
            known = list(Robot.objects.values_list("name", flat=True))
            raise CliExit(EXIT_USAGE, _("Which robot? Give ROBOT, one of: %(known)s.") % {
                "known": out.sample(known, _("see the admin"))})
        return opts.robot_name or opts.robot

    def listed(self, robot: Robot | None, include_lost: bool) -> list[ManagedNode]:
        nodes = ManagedNode.objects.select_related("robot__gateway")
        if robot is not None:
            nodes = nodes.filter(robot=robot)
        return list(nodes if include_lost else nodes.filter(alive=True))

    def node(self, ref: str, robot: Robot | None) -> ManagedNode:
        """A node id (agv-1.joy_to_vel) or, on ``robot``, a ROS name (/joy_to_vel, joy_to_vel)."""
        nodes = ManagedNode.objects.select_related("robot__gateway")
        if robot is None:
            found = nodes.filter(key=ref).first()
        else:
            names = {"/" + ref.strip("/")}
            if robot.namespace and not ref.startswith("/"):
                names.add(f"{robot.namespace.rstrip('/')}/{ref}")
            found = nodes.filter(robot=robot).filter(Q(key=ref) | Q(name__in=names)).first()
        if found is not None:
            return found
        if robot is None and "." in ref:  # agv-1.nope: say which nodes agv-1 has
            robot = Robot.objects.filter(name=ref.split(".", 1)[0]).first()
        if robot is not None:
            known, same_name = list(robot.nodes.values_list("name", flat=True)), []
        else:
            known = list(ManagedNode.objects.values_list("key", flat=True))
            same_name = list(nodes.filter(name="/" + ref.strip("/")).values_list("key", flat=True))
        message = out.unknown_node(ref, robot.name if robot else None, known, same_name)
        raise CliExit(EXIT_USAGE, message, "not_found")

    def transition(self, requested: str) -> str | int:
        """Checked before anything else is looked up: a mistyped name is a usage error."""
        try:
            return named(requested)
        except TransitionRefused as refused:
            raise CliExit(EXIT_USAGE, refused.message, refused.code) from None

    def user(self, username: str | None):
        """The site user a change is made as, who must be allowed to operate nodes."""
        chosen = username or os.environ.get("LIFECYCLE_USER")
        name = chosen or login_name()
        model = get_user_model()
        user = model.objects.filter(**{model.USERNAME_FIELD: name}).first() if name else None
        if user is None:
            raise CliExit(EXIT_USAGE, out.no_user(name, chosen is not None), "no_user")
        if not user.is_active or not user.has_perm("fleet.operate_node"):
            raise CliExit(EXIT_USAGE, _("Site user %(name)s may not operate nodes (inactive, or without the operator "
                                        "role).") % {"name": repr(name)}, "forbidden")
        return user


def refused_exit(exc: Refusal) -> CliExit:
    code = {"gateway_offline": EXIT_OFFLINE, "not_found": EXIT_USAGE}.get(exc.code, EXIT_FAILED)
    return CliExit(code, exc.message, exc.code)


def as_exit(exc: BaseException) -> CliExit:
    """One line and an exit status for what can go wrong beyond the verbs' own checks."""
    if isinstance(exc, GatewayOffline):
        return CliExit(EXIT_OFFLINE, exc.message, exc.code)
    if isinstance(exc, DatabaseError):
        return CliExit(EXIT_OFFLINE, _("The site's database is unreachable: %(error)s") % {"error": exc},
                       "database_error")
    return CliExit(EXIT_INTERRUPTED, _("Interrupted."))


def login_name() -> str:
    try:
        return getpass.getuser()
    except (OSError, KeyError):
        return ""

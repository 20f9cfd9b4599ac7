"""The face of ``manage.py lifecycle``: its verbs, arguments and help, and what it prints (the
shapes of ``ros2 lifecycle`` where the verbs overlap, the API's JSON shapes for ``--json``, one
line per node of a group run). The command itself is operations/management/commands/lifecycle.py.

Its human output is in German or English (languages/cli.py); its --json output is the API's, codes
and values as they are, only the messages in that language too."""
from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterable
from typing import Any

from django.core.management.base import DjangoHelpFormatter
from django.utils.text import format_lazy
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy, ngettext, pgettext

from lifecycle_site.fleet.models import GroupRun, ManagedNode
from lifecycle_site.gateway_link.gateway_client import MAX_SERVICE_TIMEOUT
from lifecycle_site.operations.runs import MAX_WAIT_S
from ros_gateway.shared import operations, protocol
from ros_gateway.shared import state_machine as sm

RUN_DETAILS = gettext_lazy("One line per node as it is done, then a summary; exit 0 only if the run succeeded.")
ROBOT_RUNS = operations.names(operations.ROBOT)
NODE_RUNS = operations.names(operations.NODE)
RUN_VERBS = (*ROBOT_RUNS, *NODE_RUNS, "mode")
MODE_ACTIONS = ("list", "show", "apply", "drift")
# Verb -> (one-line summary, details) for --help (lazy: made text in the CLI's language, add_verbs).
# (The operations' summaries, op.help, come from ros_gateway/shared/operations.py, in English.)
VERBS: dict[str, tuple[str, str]] = {
    "nodes": (gettext_lazy("list the lifecycle nodes"),
              gettext_lazy("One line per node: '/joy_to_vel' with --robot, else 'agv-1 /joy_to_vel'.")),
    "get": (gettext_lazy("print the state of a node, or of every node"),
            gettext_lazy("'unconfigured [1]' for NODE; without NODE 'agv-1 /joy_to_vel: unconfigured [1]' per node.\n"
                         "Live from the node; the last known state (with a note on stderr) when the gateway is "
                         "offline.")),
    "set": (gettext_lazy("trigger a lifecycle transition"),
            gettext_lazy("Prints 'Transitioning successful' (exit 0) or 'Transitioning failed' (exit 1, reason on "
                         "stderr).")),
    "list": (gettext_lazy("list the transitions available from the node's current state"),
             gettext_lazy("'- configure [1]', then its start and goal states; -a: the node's whole transition "
                          "graph.")),
    **{op.name: (op.help, RUN_DETAILS) for op in operations.OPERATIONS if op.startable},
    "mode": (gettext_lazy("list a robot's modes, show one, apply one, or show how the robot differs from its mode"),
             gettext_lazy("mode list ROBOT: one line per mode, the current one marked; mode show ROBOT MODE: one "
                          "line\nper node (its state, its parameters); mode apply ROBOT MODE: one run, one line per "
                          "node as it\nis done (exit 0 only if it succeeded); mode drift ROBOT: one line per "
                          "difference (exit 0 when\nthere is none, 1 when there is).")),
    "diagnostics": (gettext_lazy("print a robot's diagnostic statuses as a tree"),
                    gettext_lazy("One line per status by name path, indented: 'ERROR  Lidar: no scans for 3 s "
                                 "(/lidar_driver,\n4 s ago)'; a branch shows the worst below it. --problems: only "
                                 "ERROR, WARN and stale ones.\nExit 0 when none is in ERROR or stale, 1 when one is "
                                 "(for scripts and health checks).")),
    "process": (gettext_lazy("list a robot's supervised processes, or start, stop or restart one"),
                gettext_lazy("Without PROCESS: one line per launch profile ('drivers: running, pid 4242, 2 "
                             "restarts').\nWith PROCESS ACTION (start, stop, restart): done by the robot's gateway, "
                             "its supervisor; prints\nwhat it did (exit 0), or why not on stderr (exit 1). Stopping "
                             "does not ask: the CLI is for\npeople who mean it (the page asks first).")),
}
DESCRIPTION = format_lazy(gettext_lazy("""\
Like 'ros2 lifecycle', but against the site: every call goes through the ROS gateway (no DDS
discovery per call) and every change lands in the audit log with source "cli" and the user.

NODE is a node id as the API uses it, ROBOT.NAME (agv-1.joy_to_vel, agv-1.arm.gripper), or,
with --robot R, the node's ROS name (/joy_to_vel or joy_to_vel). Several robots may run nodes
of the same name, so lines about nodes of all robots start with the robot ("agv-1 /joy_to_vel");
with --robot they show the ROS name only ("/joy_to_vel"), as ros2 does.

Changing verbs (set and the operations: {verbs}) act as --user USERNAME,
else $LIFECYCLE_USER, else the site user named like your login; that user must be active and
allowed to operate nodes. Read-only verbs (nodes, get, list) need no user."""), verbs=", ".join(RUN_VERBS))
EPILOG = gettext_lazy("""\
exit status: 0 success; 1 the transition or run failed (or was still running after --wait);
2 usage error, unknown node, robot or transition, no usable user; 3 gateway offline or Redis
unreachable; 130 interrupted (Ctrl-C).

examples:
  manage.py lifecycle nodes --robot agv-1
  manage.py lifecycle get agv-1.joy_to_vel
  manage.py lifecycle set --robot agv-1 /joy_to_vel configure
  manage.py lifecycle list agv-1.joy_to_vel -a
  manage.py lifecycle bringup agv-1 --policy continue --timeout 10 --json
  manage.py lifecycle process agv-1 drivers restart
  manage.py lifecycle mode apply agv-1 production
  manage.py lifecycle diagnostics agv-2 --problems""")

NODE_HELP = gettext_lazy("node id (agv-1.joy_to_vel), or with --robot its ROS name (/joy_to_vel)")
# How many known names an "unknown node/robot" message lists.
SAMPLE = 10


# --- arguments and help ----------------------------------------------------------------


class HelpFormatter(DjangoHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Django's option order, with the description's paragraphs kept as written."""


def seconds(limit: float):
    """An argparse type: a positive number of seconds up to ``limit``."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(_("%(text)s is not a number of seconds") % {"text": repr(text)}) from None
        if not math.isfinite(value) or value <= 0 or value > limit:
            raise argparse.ArgumentTypeError(_("give a number of seconds above 0 and at most %(most)s") % {
                "most": f"{limit:g}"})
        return value

    return parse


def option_sets() -> tuple[argparse.ArgumentParser, ...]:
    """Options of every verb; of the verbs that call nodes; of the group runs."""
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", help=_("machine-readable output (the API's JSON shapes)"))
    common.add_argument("--robot", metavar="R", help=_("the robot; NODE may then be a ROS name such as /joy_to_vel"))
    common.add_argument("--user", metavar="USERNAME",
                        help=_("who makes changes, for the audit log (default: $LIFECYCLE_USER, else your login)"))
    service = argparse.ArgumentParser(add_help=False)
    service.add_argument("--timeout", metavar="S", type=seconds(MAX_SERVICE_TIMEOUT),
                         help=_("bound (s) on each call to a node, sent to the gateway (<= %(most)s)") % {
                             "most": f"{MAX_SERVICE_TIMEOUT:g}"})
    run = argparse.ArgumentParser(add_help=False)
    run.add_argument("--policy", choices=GroupRun.Policy.values, default=GroupRun.Policy.STOP,
                     help=_("stop at the first failing node (default) or continue and report"))
    run.add_argument("--timeout", metavar="S", type=seconds(MAX_WAIT_S), help=_("per-node timeout (s), default 5"))
    run.add_argument("--wait", metavar="S", type=seconds(MAX_WAIT_S), default=120.0,
                     help=_("how long to follow the run (s, default 120); it goes on in the gateway anyway"))
    return common, service, run


def _verb_texts() -> list[tuple[str, str, str]]:
    """Each verb's name, summary and details as text in the active language (an operation's
    summary, op.help, is English in ros_gateway/shared/operations.py: translated when the
    catalogue has it, as the pages mark it)."""
    return [(name, _(summary) if type(summary) is str else str(summary), str(details))
            for name, (summary, details) in VERBS.items()]


def add_verbs(parser: argparse.ArgumentParser) -> None:
    """The verbs and their arguments (their help in the language active now: languages/cli.py)."""
    common, service, run = option_sets()
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB", title=_("verbs"))
    sub = {
        name: verbs.add_parser(name, parents=[common, run if name in RUN_VERBS else service], help=summary,
                               description=f"{summary}\n\n{details}", formatter_class=HelpFormatter)
        for name, summary, details in _verb_texts()
    }
    node_help = str(NODE_HELP)
    sub["nodes"].add_argument("-a", "--all", action="store_true", help=_("also nodes not running now, marked (lost)"))
    sub["nodes"].add_argument("-c", "--count-nodes", action="store_true", help=_("only print the number of nodes"))
    sub["get"].add_argument("node", nargs="?", metavar="NODE", help=node_help)
    sub["get"].add_argument("-a", "--all", action="store_true", help=_("without NODE: also nodes not running, (lost)"))
    for name in ("set", "list", *NODE_RUNS):
        sub[name].add_argument("node", metavar="NODE", help=node_help)
    sub["set"].add_argument("transition", metavar="TRANSITION", help=_("label (configure) or numeric id (1)"))
    sub["list"].add_argument("-a", "--all", action="store_true", help=_("the node's whole transition graph"))
    for name in ROBOT_RUNS:
        sub[name].add_argument("robot_name", nargs="?", metavar="ROBOT", help=_("the robot (or --robot R)"))
    sub["mode"].add_argument("action", choices=MODE_ACTIONS, metavar="ACTION", help=", ".join(MODE_ACTIONS))
    sub["mode"].add_argument("robot_name", metavar="ROBOT", help=_("the robot"))
    sub["mode"].add_argument("mode", nargs="?", metavar="MODE", help=_("the mode (show, apply)"))
    sub["diagnostics"].add_argument("robot_name", metavar="ROBOT", help=_("the robot"))
    sub["diagnostics"].add_argument("--problems", action="store_true", help=_("only statuses in WARN, ERROR or stale"))
    sub["process"].add_argument("robot_name", metavar="ROBOT", help=_("the robot"))
    sub["process"].add_argument("process", nargs="?", metavar="PROCESS", help=_("a launch profile's name"))
    sub["process"].add_argument("action", nargs="?", choices=protocol.PROCESS_ACTIONS, metavar="ACTION",
                                help=_("start, stop or restart"))


# --- output --------------------------------------------------------------------------


def to_json(data: Any) -> str:
    return json.dumps(data, indent=2, ensure_ascii=False)


def state_text(state: dict) -> str:
    """``unconfigured [1]``, as ``ros2 lifecycle get`` prints a state."""
    return f"{state['label']} [{state['id']}]"


def node_label(node: ManagedNode, with_robot: bool) -> str:
    """``/joy_to_vel`` when the robot is implied (--robot), else ``agv-1 /joy_to_vel``."""
    return f"{node.robot.name} {node.name}" if with_robot else node.name


def lost_mark(node: ManagedNode) -> str:
    if node.alive:
        return ""
    mark = pgettext("node", "unreachable") if node.gone_reason == "unreachable" else pgettext("node", "lost")
    return f" ({mark})"


def node_json(node: ManagedNode, state: dict | None = None, **extra: Any) -> dict:
    """The API's node shape (GET /api/v1/nodes), optionally with a freshly read state."""
    payload = protocol.node_payload(
        key=node.key,
        robot=node.robot.name,
        name=node.name,
        state_id=(state or node.state)["id"],
        alive=node.alive,
        gone_reason=node.gone_reason,
        last_seen=node.last_seen.isoformat() if node.last_seen else None,
        process_status=node.process_status,
        process_since=node.process_since.isoformat() if node.process_since else None,
    )
    return {**payload, **extra}


def transition_lines(transitions: Iterable[dict]) -> list[str]:
    """``ros2 lifecycle list``: ``- configure [1]``, then its start and goal states."""
    lines = []
    for t in transitions:
        lines += [f"- {t['label']} [{t['id']}]", "\t" + _("Start: %(state)s") % {"state": t["start"]["label"]},
                  "\t" + _("Goal: %(state)s") % {"state": t["goal"]["label"]}]
    return lines


def available_lines(state_id: int, valid: list[dict] | None = None) -> list[str]:
    """The transitions valid from a state, as ``ros2 lifecycle set`` lists them."""
    valid = valid if valid is not None else [t.as_dict() for t in sm.valid_transitions(state_id)]
    state = {"state": sm.state_label(state_id)}
    if not valid:
        return [_("No transition is possible from %(state)s.") % state]
    return [_("Available transitions from %(state)s:") % state] + [
        f"- {t['label']} [{t['id']}]" for t in valid
    ]


def sample(names: list[str], everything_hint: str) -> str:
    """``a, b, c`` or ``a, ..., j and 5 more (HINT)``."""
    if not names:
        return pgettext("list of names", "none")
    if len(names) <= SAMPLE:
        return ", ".join(names)
    more = len(names) - SAMPLE
    return ngettext("%(names)s and %(more)s more (%(hint)s)", "%(names)s and %(more)s more (%(hint)s)", more) % {
        "names": ", ".join(names[:SAMPLE]), "more": more, "hint": everything_hint}


# --- group runs (results as ros_gateway/groups.py writes them) ---------------------------


def _step_text(step: dict) -> str:
    """``configure ok``, ``activate FAILED: reason``, ``configure TIMED OUT: reason``."""
    if step["outcome"] == "succeeded":
        return f"{step['transition']} ok"
    word = _("TIMED OUT") if step["outcome"] == "timed_out" else _("FAILED")
    return f"{step['transition']} {word}" + (f": {step['message']}" if step.get("message") else "")


def result_line(result: dict) -> str:
    """``/lidar_driver: configure ok, activate ok (12 ms)``, ``... FAILED: reason``, ``skipped (...)``."""
    name, outcome, message = result["node"], result["outcome"], result.get("message") or ""
    if outcome == "skipped":  # (the message is the gateway's, in English)
        if message:
            return _("%(node)s: skipped (%(reason)s)") % {"node": name, "reason": message}
        return _("%(node)s: skipped") % {"node": name}
    if outcome == "not_run":
        return _("%(node)s: not run (%(reason)s)") % {"node": name, "reason": message.removeprefix("not run: ")}
    parts = [_step_text(step) for step in result.get("steps", [])]
    if outcome == "failed" and not any(step["outcome"] != "succeeded" for step in result.get("steps", [])):
        parts.append(_("FAILED: %(reason)s") % {"reason": message} if message else _("FAILED"))
    took = f" ({result['duration_ms']:.0f} ms)" if outcome == "succeeded" and "duration_ms" in result else ""
    return f"{name}: {', '.join(parts) or outcome}{took}"


def summary_line(run: GroupRun) -> str:
    """``bringup agv-1: succeeded (2 succeeded, 1 skipped) in 1.2 s``; a mode's run names the mode
    (``mode mapping on agv-1: ...``)."""
    mode = run.plan.get("mode") if isinstance(run.plan, dict) else None
    if mode:
        what = _("mode %(mode)s on %(robot)s") % {"mode": mode, "robot": run.robot.name}
    else:
        what = f"{run.operation} {run.robot.name}"
    line = f"{what}: {run.get_status_display()}"
    if run.message:  # (stored, in English)
        line += f" ({run.message})"
    if run.started and run.finished:
        line = _("%(summary)s in %(seconds)s s") % {
            "summary": line, "seconds": f"{(run.finished - run.started).total_seconds():.1f}"}
    return line


def no_user(name: str, chosen: bool) -> str:
    if chosen:
        return _("There is no site user %(name)s to record in the audit log.") % {"name": repr(name)}
    return _("No site user to record in the audit log: give --user USERNAME or set LIFECYCLE_USER (your login "
             "name %(name)s is not a user of the site).") % {"name": repr(name)}


def unknown_robot(name: str, known: list[str]) -> str:
    return _("There is no robot %(name)s. Known robots: %(known)s.") % {
        "name": repr(name), "known": sample(known, _("see the admin"))}


def unknown_node(ref: str, robot: str | None, known: list[str], same_name: list[str]) -> str:
    """Why ``ref`` names no node; ``known``: the robot's node names, or every node id without a
    robot; ``same_name``: ids of nodes whose ROS name is ``ref`` (a ROS name given without --robot)."""
    if robot is not None:
        return _("Robot %(robot)s has no node %(node)s. Its nodes: %(known)s.") % {
            "robot": robot, "node": repr(ref), "known": sample(known, "lifecycle nodes -a --robot " + robot)}
    if same_name:
        return _("There is no node id %(node)s; a ROS name needs --robot R. Node ids of that name: %(ids)s.") % {
            "node": repr(ref), "ids": sample(same_name, "lifecycle nodes -a")}
    return _("There is no node %(node)s. Node ids look like ROBOT.NAME; known: %(known)s.") % {
        "node": repr(ref), "known": sample(known, "lifecycle nodes -a")}


def process_line(profile: Any, usage: dict | None = None) -> str:
    """``drivers: running, pid 4242, 2 restarts`` (and the last exit, when there was one); a
    launch profile, or a container or unit (operations.processes.HostProcess)."""
    parts = [profile.get_status_display()]
    if profile.pid:
        parts.append(f"pid {profile.pid}")
    if profile.restarts:
        parts.append(ngettext("%(n)s restart", "%(n)s restarts", profile.restarts) % {"n": profile.restarts})
    exit_ = profile.as_dict()["last_exit"]
    if exit_ is not None:
        how = exit_["signal"] or _("status %(code)s") % {"code": exit_["code"]}
        parts.append(_("last exit: %(how)s at %(at)s UTC") % {"how": how, "at": exit_["at"][:19].replace("T", " ")})
    if usage:  # measured by the gateway just now
        cpu = "-" if usage["cpu_percent"] is None else f"{usage['cpu_percent']:.1f} %"
        parts.append(f"CPU {cpu}, {usage['rss_mb']:.0f} MB")
    if getattr(profile, "nodes", None):  # a container or unit: what runs in it
        parts.append(_("nodes: %(nodes)s") % {"nodes": ", ".join(profile.nodes)})
    if not profile.enabled:
        return _("%(process)s: %(parts)s (disabled)") % {"process": profile.name, "parts": ", ".join(parts)}
    return f"{profile.name}: {', '.join(parts)}"


def mode_lines(modes: list[dict], current: str | None, since: str | None) -> list[str]:
    lines = []
    for mode in modes:
        name = mode["name"]
        if name == current:
            name = _("%(mode)s (current since %(since)s)") % {"mode": name, "since": since}
        count = len(mode["nodes"])
        nodes = ngettext("%(n)s node", "%(n)s nodes", count) % {"n": count}
        about = f": {mode['description'].splitlines()[0]}" if mode["description"] else ""
        lines.append(f"{name}, {nodes}{about}")
    return lines or [_("(no modes; an admin defines them)")]


def mode_node_lines(mode: dict) -> list[str]:
    lines = []
    for name, entry in mode["nodes"].items():
        values = ", ".join(f"{key}={value!r}" for key, value in (entry.get("parameters") or {}).items())
        state = entry.get("state") or _("left alone")
        lines.append(f"{name}: {state}" + (f"; {values}" if values else ""))
    return lines



def diagnostic_lines(rows: list[dict], robot: str, now: Any, statuses: int) -> list[str]:
    """``ERROR  Lidar: no scans (/lidar_driver, 4 s ago)``, indented by depth (the API's tree rows)."""
    from datetime import datetime

    lines = []
    for row in rows:
        status = row["status"]
        text = f"{'  ' * row['depth']}{row['shown']:<5}  {row['label']}"
        if status is None:
            lines.append(text)
            continue
        heard = int((now - datetime.fromisoformat(status["heard"])).total_seconds())
        where = ", ".join(filter(None, (status["node"], _("%(n)s s ago") % {"n": max(heard, 0)})))
        lines.append(f"{text}: {status['message'] or '-'} ({where})")
    if not lines and statuses:
        return [_("Every diagnostic status of %(robot)s is OK (%(count)s).") % {"robot": robot, "count": statuses}]
    return lines or [_("No diagnostics heard from %(robot)s yet.") % {"robot": robot}]

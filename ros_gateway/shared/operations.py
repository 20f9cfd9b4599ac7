"""The robot operations, declared once: what each does, in which order, what it leaves alone,
how it is named, explained and confirmed, and who may start it.

The gateway drives a run by its ``phases`` (ros_gateway/groups.py); the site reads the same
table for the run model's choices, the API's and the CLI's verbs and messages, the fleet
page's buttons and confirmations, and docs/operations.md (written from it: ``python -m
ros_gateway.shared.operations``). Adding an operation is one entry here; one that needs more
than phases of target states also gets a handler in groups.py.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

from ros_gateway.shared import state_machine as sm

# Who an operation is for (Operation.scope); MODE: a robot's nodes, each to its own target (a mode's)
ROBOT, NODE, GATEWAY, MODE = "robot", "node", "gateway", "mode"
EACH_NODES_OWN = -1  # Phase.target: each node to the target the run names for it
DOWN, UP = "down", "up"  # Phase.only: the nodes whose target is below (above) their state


def _(text: str) -> str:
    """Marks a text for the site's translation catalogue (Django's makemessages finds ``_``)
    without translating it: the gateway has no Django. The site translates the operation's
    words when it shows them (lifecycle_site/operations/words.py)."""
    return text


@dataclass(frozen=True)
class Phase:
    """Every node of the run driven to ``target``: in the robot's bring-up order, or in reverse;
    a node in one of ``leave_alone`` is skipped (not failed). ``only``: with EACH_NODES_OWN, the
    phase moves only the nodes going that way (a mode takes nodes down in reverse order, then up)."""

    target: int
    reverse: bool = False
    leave_alone: tuple[int, ...] = ()
    only: str = ""


@dataclass(frozen=True)
class Operation:
    name: str  # on the wire, in the API, the CLI verb
    button: str  # the fleet page's button ("Bring up")
    title: str  # a run of it, as its panel and the audit name it ("Bring-up")
    help: str  # one line: CLI --help, docs
    phases: tuple[Phase, ...]  # empty: the gateway works out the target itself (recovery)
    scope: str = ROBOT  # ROBOT: all (or the named) nodes of a robot; NODE: one; MODE: see above; GATEWAY: its own
    confirm: str = ""  # asked before it starts; {nodes} is the count of nodes, {robot} the robot's name
    confirm_detail: str = ""
    danger: bool = False  # shown as a destructive button
    role: str = "operator"  # the least role that may start it (site roles: viewer, operator, admin)

    @property
    def startable(self) -> bool:
        """Started by name (a mode's run is started by applying the mode; a recovery by the gateway)."""
        return self.scope in (ROBOT, NODE)

    def confirm_text(self, robot: str, mode: str = "") -> str:
        """The question with the robot's (and mode's) name in it; ``{nodes}`` is left for the page to count."""
        return self.confirm.replace("{robot}", robot).replace("{mode}", mode)


_UP = Phase(sm.ACTIVE)
_DOWN_TO_UNCONFIGURED = Phase(sm.UNCONFIGURED, reverse=True)

OPERATIONS: tuple[Operation, ...] = (
    Operation("bringup", _("Bring up"), _("Bring-up"),
              _("bring the robot's nodes up: configure, then activate, in order"), (_UP,)),
    Operation("pause", _("Pause"), _("Pause"), _("deactivate the robot's nodes, in reverse order"),
              (Phase(sm.INACTIVE, reverse=True, leave_alone=(sm.UNCONFIGURED,)),)),
    Operation("resume", _("Resume"), _("Resume"), _("activate the robot's nodes, in order"),
              (Phase(sm.ACTIVE, leave_alone=(sm.UNCONFIGURED,)),)),
    Operation("reset", _("Reset"), _("Reset"), _("deactivate and clean up the robot's nodes, in reverse order"),
              (_DOWN_TO_UNCONFIGURED,),
              confirm=_("Reset {nodes} of {robot} to unconfigured?"),
              confirm_detail=_("Active nodes are deactivated first; each must be configured again before it works.")),
    Operation("restart_all", _("Restart all"), _("Full restart"),
              _("take the robot's nodes down to unconfigured in reverse order, then bring them up in order"),
              (_DOWN_TO_UNCONFIGURED, _UP),
              confirm=_("Restart {nodes} of {robot}?"),
              confirm_detail=_("Each is deactivated and cleaned up (in reverse order), then configured and "
              "activated again in order; the robot's nodes stop working meanwhile.")),
    Operation("shutdown", _("Shut down"), _("Shut-down"), _("shut the robot's nodes down, in reverse order"),
              (Phase(sm.FINALIZED, reverse=True),), danger=True,
              confirm=_("Shut down {nodes} of {robot}?"),
              confirm_detail=_("They end finalized; only a restart of their processes brings them back.")),
    Operation("restart", _("Restart"), _("Restart"), _("bring a node back to active from whatever state it is in"),
              (_DOWN_TO_UNCONFIGURED, _UP), scope=NODE),
    Operation("mode", _("Apply"), _("Mode change"),
              _("drive each node to its state in a mode (down in reverse order, then up in order), its "
              "parameters set before it is activated"),
              (Phase(EACH_NODES_OWN, reverse=True, only=DOWN), Phase(EACH_NODES_OWN, only=UP)), scope=MODE,
              confirm=_("Apply mode {mode} to {robot}?"),
              confirm_detail=_("Nodes are taken to the mode's states and parameters; the run lists every change.")),
    Operation("recover", _("Recover"), _("Recovery"),
              _("bring a node whose process was restarted back to its desired state (the gateway starts it)"),
              (), scope=GATEWAY),
)
BY_NAME: dict[str, Operation] = {op.name: op for op in OPERATIONS}


def get(name: object) -> Operation | None:
    return BY_NAME.get(name) if isinstance(name, str) else None


def names(scope: str | None = None) -> list[str]:
    """Startable operations (of one scope, if given), in the table's order."""
    return [op.name for op in OPERATIONS if op.startable and (scope is None or op.scope == scope)]


def choices() -> list[tuple[str, str]]:
    """For the run model's field: every operation, the gateway's own included."""
    return [(op.name, op.title) for op in OPERATIONS]


def _target_words(phase: Phase) -> str:
    if phase.target != EACH_NODES_OWN:
        return sm.state_label(phase.target)
    return f"each to its own, those going {phase.only}" if phase.only else "each to its own"


def markdown() -> str:
    """docs/operations.md (a unit test keeps the file equal to this)."""
    lines = [
        "# Robot operations",
        "",
        "Written from `ros_gateway/shared/operations.py` by `python -m ros_gateway.shared.operations`;",
        "do not edit by hand. Every operation is started the same way from the fleet page (its button),",
        "the API (`POST /api/v1/robots/{name}/operations` with `{\"operation\": NAME}`; a node's restart:",
        "`POST /api/v1/nodes/{id}/restart`) and the command line (`manage.py lifecycle NAME ROBOT`).",
        "How the nodes are ordered and what a failure stops: docs/api.md, \"ordered group operations\".",
        "",
        "| Name | Button | What it does | Phases (target, order; left alone) | For | Asks first | Role |",
        "|---|---|---|---|---|---|---|",
    ]
    for op in OPERATIONS:
        phases = "; ".join(
            f"{_target_words(p)}, {'reverse' if p.reverse else 'in order'}"
            + (f"; leaves {', '.join(sm.state_label(s) for s in p.leave_alone)} alone" if p.leave_alone else "")
            for p in op.phases) or "the node's desired state"
        scope = {ROBOT: "a robot's nodes (or the named ones)", NODE: "one node",
                 GATEWAY: "started by the gateway only", MODE: "a robot's nodes, as a mode says"}[op.scope]
        asks = (op.confirm.replace("{nodes}", "N nodes").replace("{robot}", "ROBOT").replace("{mode}", "MODE")
                if op.confirm else "-")
        lines.append(f"| `{op.name}` | {op.button} | {op.help} | {phases} | {scope} | {asks} | {op.role} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(markdown())

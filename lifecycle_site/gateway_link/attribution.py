"""Who asked for a change, as the site vouches for it to the gateway and back.

A command the site sends for a person (a transition, parameters) carries a grant: an HMAC, with
a key only the site knows (Django's SECRET_KEY, salted), of the request's id, user, source,
robot, node and what was asked (the transition's label; for parameters one grant per name). The
gateway copies it into the audit fact of what it did for that command, whose id is then the
request's (``protocol.vouching``), so a grant makes at most one record (two for a transition:
the site's own "not answered" beside the gateway's). The site takes a fact's user and source
(dashboard, API, command line) only with a grant that checks out. So a gateway, which is a
stranger, cannot put a change of its own on anybody's name, nor make it look as if it came from
the dashboard. Facts without a grant may only say "external" (another tool) or "recovery" (the
gateway's own automatic recovery), with no user; steps of a group run take who and how from the
run the site made, while it is under way and for its own nodes.
"""
from __future__ import annotations

from datetime import timedelta
from typing import Any

from django.conf import settings
from django.utils import timezone
from django.utils.crypto import constant_time_compare, salted_hmac

from ros_gateway.shared import protocol

# Part of the grants' key (salted_hmac), not a module path: changing it voids every grant in flight
# (their records would lose who asked), so it keeps the name of the module that first held it.
SALT = "lifecycle_site.fleet.attribution"
GATEWAY_SOURCES = ("external", "recovery")  # what a gateway may say on its own
GATEWAY_PROCESS_SOURCES = ("supervisor", "config", "external")  # ... of a supervised process


def _message(request_id: Any, user_id: Any, source: Any, robot: Any, node: Any, what: Any) -> str:
    text = "\0".join(str(part) for part in (request_id, user_id, source, robot, node, what))
    return text.encode("utf-8", "surrogatepass").decode("utf-8", "replace")  # (a name with a lone surrogate)


def grant(request_id: str, user_id: int | None, source: str, robot: str, node: str, what: str,
          secret: str | None = None) -> str:
    """``what``: "transition:LABEL" or "parameter:NAME"."""
    return salted_hmac(SALT, _message(request_id, user_id, source, robot, node, what), secret=secret,
                       algorithm="sha256").hexdigest()[:40]


def grants_for(command: dict) -> dict:
    """The grant fields a command of the site carries (none for a command that is not audited)."""
    common = (command["request_id"], command.get("user_id"), str(command.get("source") or "api"),
              str(command.get("robot")), str(command.get("node")))
    if command["command"] == protocol.PROCESS_CONTROL:  # (the process's name where a node's would be)
        return {"grant": grant(*common[:4], str(command.get("process")), f"process:{command.get('action')}")}
    if command["command"] == protocol.CHANGE_STATE:
        return {"grant": grant(*common, f"transition:{protocol.transition_word(command.get('transition'))}")}
    if command["command"] == protocol.SET_PARAMETERS and isinstance(command.get("values"), dict):
        return {"grants": {str(name): grant(*common, f"parameter:{name}") for name in command["values"]}}
    return {}


def vouched(fact: dict) -> bool:
    """Whether the fact's user and source come with the site's grant for its request and for
    what it records, under the one id that grant allows (the current key or one it was rotated
    from, SECRET_KEY_FALLBACKS)."""
    found, request_id = fact.get("grant"), fact.get("request_id")
    if not isinstance(found, str) or not isinstance(request_id, str):
        return False
    node = fact.get("node")
    if fact.get("type") == protocol.TRANSITION:
        what = f"transition:{fact.get('transition_label')}"
        ids = (request_id, protocol.unanswered_id(request_id))
    elif fact.get("type") == protocol.PROCESS:
        what, node = f"process:{fact.get('action')}", fact.get("process")
        ids = (request_id,)
    else:
        what = f"parameter:{fact.get('name')}"
        ids = (protocol.parameter_fact_id(request_id, str(fact.get("name"))),)
    if fact.get("id") not in ids:
        return False
    for secret in (settings.SECRET_KEY, *getattr(settings, "SECRET_KEY_FALLBACKS", [])):
        expected = grant(request_id, fact.get("user_id"), fact.get("source"), fact.get("robot"), node, what,
                         secret=secret)
        if constant_time_compare(expected, found):
            return True
    return False


def requester(known: Any, fact: dict, robot: Any) -> tuple[str, int | None, str]:
    """(source, user id, note) of an audit fact, as far as the site can vouch for them: a step of
    a group run is the run's (the site made it, or it is the gateway's own recovery); a command's
    record needs the site's grant; anything else is the gateway's own word, which may only be
    "external" or "recovery", with nobody's name. A claim the site cannot vouch for is not taken:
    the record is kept (the change reached a robot) as "external", without a user, and the note
    says what the gateway claimed. Raises FactRejected for a run of another robot."""
    from lifecycle_site.audit.models import TransitionRecord
    from lifecycle_site.fleet.models import GroupRun
    from lifecycle_site.gateway_link import gateway_input as checks

    source = checks.choice(fact.get("source"), TransitionRecord.Source.values, "source")
    user_id = checks.user_id(fact.get("user_id"))
    run_id = fact.get("run_id") or ""
    if run_id:
        runs = known.__dict__.setdefault("runs", {})
        if run_id not in runs:
            runs[run_id] = GroupRun.objects.filter(pk=run_id).values(
                "robot_id", "source", "requested_by_id", "only_nodes", "plan", "created", "finished").first()
        run = runs[run_id]
        if run is None or run["robot_id"] != robot.id:
            raise checks.GatewayInputRefused(f"run {str(run_id)[:32]} is not one of robot {robot.name}'s runs")
        if not fact.get("grant"):
            if _within(run, fact):
                run_source = run["source"] if run["source"] in TransitionRecord.Source.values else "api"
                return run_source, run["requested_by_id"], ""
            return "external", None, f" (the gateway said it was a step of run {run_id[:8]}, which it is not)"
    return _as_vouched(fact, source, user_id, GATEWAY_SOURCES)


def _as_vouched(fact: dict, source: str, user_id: int | None, own: tuple[str, ...]) -> tuple[str, int | None, str]:
    """The fact's source and user if the gateway may say them on its own (``own``, nobody's
    name) or the site's grant vouches for them; else "external", and what the gateway claimed."""
    if source in own and user_id is None:
        return source, None, ""
    if vouched(fact):
        return source, user_id, ""
    claimed = f"source {source}" + (f", user #{user_id}" if user_id is not None else "")
    return "external", None, f" (the gateway said {claimed}; the site sent it no such request)"


def process_requester(known: Any, fact: dict) -> tuple[str, int | None, str]:
    """(source, user id, note) of a ``process`` fact, as requester() does for transitions: a user
    and a person's source only with the site's grant; on its own word the gateway may say only
    that its supervisor acted by itself, or on a changed profile."""
    from lifecycle_site.audit.models import ProcessRecord
    from lifecycle_site.gateway_link import gateway_input as checks

    source = checks.choice(fact.get("source"), ProcessRecord.Source.values, "source")
    return _as_vouched(fact, source, checks.user_id(fact.get("user_id")), GATEWAY_PROCESS_SOURCES)


RUN_SLACK = timedelta(seconds=5)


def _within(run: dict, fact: dict) -> bool:
    """Whether a step is one of the run's: one of its nodes, asked for while it was under way."""
    from lifecycle_site.gateway_link import gateway_input as checks

    if run["only_nodes"] and fact.get("node") not in run["only_nodes"]:
        return False
    if fact.get("type") == protocol.PARAMETER:
        # Only a value the run's mode sets, on its node: a gateway cannot put another change on the run.
        wanted = (run["plan"].get("parameters") or {}).get(fact.get("node")) or {}
        if fact.get("name") not in wanted or wanted[fact.get("name")] != fact.get("new"):
            return False
    try:
        asked = checks.moment(fact.get("requested_at") or fact.get("at"), "requested_at")
    except checks.GatewayInputRefused:
        return False
    return run["created"] - RUN_SLACK <= asked <= (run["finished"] or timezone.now()) + RUN_SLACK

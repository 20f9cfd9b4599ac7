"""Who asked for a change, as the site vouches for it to the gateway and back.

A command the site sends for a person (a transition, parameters) carries a grant: an HMAC, with
a key only the site knows (Django's SECRET_KEY, salted), of the request's id, user, source,
robot and node. The gateway copies it into the audit facts of what it did for that command; the
site takes a fact's user and source (dashboard, API, command line) only with a grant that checks
out. So a gateway, which is a stranger, cannot put a change of its own on anybody's name, nor
make it look as if it came from the dashboard. Facts without a grant may only say "external"
(another tool) or "recovery" (the gateway's own automatic recovery), with no user; steps of a
group run take who and how from the run the site made.
"""
from __future__ import annotations

from typing import Any

from django.conf import settings
from django.utils.crypto import constant_time_compare, salted_hmac

SALT = "lifecycle_site.fleet.attribution"
GATEWAY_SOURCES = ("external", "recovery")  # what a gateway may say on its own


def _message(request_id: Any, user_id: Any, source: Any, robot: Any, node: Any) -> str:
    return "\0".join(str(part) for part in (request_id, user_id, source, robot, node))


def grant(request_id: str, user_id: int | None, source: str, robot: str, node: str, secret: str | None = None) -> str:
    return salted_hmac(SALT, _message(request_id, user_id, source, robot, node), secret=secret,
                       algorithm="sha256").hexdigest()[:40]


def vouched(fact: dict) -> bool:
    """Whether the fact's user and source come with the site's grant for its request (the
    current key or one it was rotated from, SECRET_KEY_FALLBACKS)."""
    found = fact.get("grant")
    request_id = fact.get("request_id") or fact.get("id")
    if not isinstance(found, str) or not isinstance(request_id, str):
        return False
    for secret in (settings.SECRET_KEY, *getattr(settings, "SECRET_KEY_FALLBACKS", [])):
        expected = grant(request_id, fact.get("user_id"), fact.get("source"), fact.get("robot"), fact.get("node"),
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
    from lifecycle_site.fleet import gateway_input as checks
    from lifecycle_site.fleet.models import GroupRun

    source = checks.choice(fact.get("source"), TransitionRecord.Source.values, "source")
    user_id = checks.user_id(fact.get("user_id"))
    run_id = fact.get("run_id") or ""
    if run_id and not fact.get("grant"):
        runs = known.__dict__.setdefault("runs", {})
        if run_id not in runs:
            runs[run_id] = GroupRun.objects.filter(pk=run_id).values("robot_id", "source", "requested_by_id").first()
        run = runs[run_id]
        if run is None or run["robot_id"] != robot.id:
            raise checks.GatewayInputRefused(f"run {str(run_id)[:32]} is not one of robot {robot.name}'s runs")
        return run["source"] if run["source"] in TransitionRecord.Source.values else "api", run["requested_by_id"], ""
    if source in GATEWAY_SOURCES and user_id is None:
        return source, None, ""
    if vouched(fact):
        return source, user_id, ""
    claimed = f"source {source}" + (f", user #{user_id}" if user_id is not None else "")
    return "external", None, f" (the gateway said {claimed}; the site sent it no such request)"

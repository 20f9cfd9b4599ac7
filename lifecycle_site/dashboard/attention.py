"""What needs attention on the fleet page: the strip at its top (templates/dashboard/_attention.html),
the marker on each affected row and the "needs attention" state filter (fleet.js), the count in
the page's title. A node whose activation just failed must not look like a healthy one.

Worst first: a gateway offline or quarantined (it takes all its robots with it: it leads, or a
fleet with many failing nodes would push it out of the strip), a failed last transition, a node
left alone after a fight with another manager, a node not in its desired state (its mode's, if
its robot is in one), one whose parameters differ from its robot's mode, a node lost or not
answering, a process lost, an alert firing; each with the node's own reason (the failure text of
its last audit record) and a link.

Cheap at size: four queries whatever the fleet's size (the nodes with their last record's
outcome, the firing alerts, the last records of the nodes listed, diagnostics in ERROR or stale),
and for robots in a mode one more and a few per robot whose mode sets parameters (at most
MODE_ROBOTS), kept KEEP_S for every page of the process; the fleet socket asks after node updates
and every few seconds
(consumers.FleetConsumer), and sends the strip only when it changed."""
from __future__ import annotations

from django.core.cache import cache
from django.db.models import OuterRef, Q, Subquery
from django.utils.translation import get_language, gettext, gettext_noop

from lifecycle_site.alerts.models import Alert
from lifecycle_site.audit.models import TransitionRecord
from lifecycle_site.dashboard import snapshots
from lifecycle_site.diagnostics.models import ERROR, STALE
from lifecycle_site.diagnostics.models import Status as DiagnosticStatus
from lifecycle_site.fleet.models import ManagedNode
from lifecycle_site.modes import drift
from lifecycle_site.modes.models import CurrentMode

FAILED, FIGHT, NOT_DESIRED, DRIFT, LOST, PROCESS_LOST, DIAGNOSTIC, ALERT, GATEWAY = (
    "failed", "fight", "not_desired", "drift", "lost", "process_lost", "diagnostic", "alert", "gateway")
RANK = {kind: i for i, kind in enumerate(
    (GATEWAY, FAILED, FIGHT, NOT_DESIRED, DRIFT, LOST, PROCESS_LOST, DIAGNOSTIC, ALERT))}
DIAGNOSTICS = 50  # ERROR and stale statuses the strip's count takes in (the worst, the latest first)
MODE_ROBOTS = 100  # robots in a mode whose parameter drift the strip works out
FAILED_OUTCOMES = (TransitionRecord.Outcome.FAILED, TransitionRecord.Outcome.TIMED_OUT)
OUTCOME_LABELS = dict(TransitionRecord.Outcome.choices)
SHOWN = 12  # items the strip lists; the filter shows every affected row
KEEP_S = 0.5
REASON_CHARS = 400
# A failed last transition's label by its outcome: with the transition's name, and without one.
FAILED_LABELS = {
    TransitionRecord.Outcome.FAILED: (gettext_noop("%(transition)s failed"), gettext_noop("transition failed")),
    TransitionRecord.Outcome.TIMED_OUT: (gettext_noop("%(transition)s timed out"),
                                         gettext_noop("transition timed out")),
}
GATEWAY_LABELS = {"quarantined": gettext_noop("gateway quarantined"), "never": gettext_noop("gateway never reported")}
ALERT_FIRING = gettext_noop("alert firing: %(rule)s")

# The strip is read once for every page whatever its language (current() is kept KEEP_S), so its
# own words are kept as said() makes them: English text and values, which view() translates at
# render time (in the page's, or the socket's, language). Each item has "label", "also" (and
# "reason") in English, and "said": the same as said() pairs.
Said = tuple[str, dict | None]


def said(text: str, **values) -> Said:
    """Words of the strip: a marked English text (gettext_noop) and its values."""
    return text, values


def plain(text: str) -> Said:
    """Words that are not translated (a stored text, or none)."""
    return text, None


def english(words: Said) -> str:
    text, values = words
    return text % values if values else text


def say(words: Said) -> str:
    """In the active language."""
    text, values = words
    if values is None:
        return text
    return gettext(text) % values if values else gettext(text)


def current(gateway_views: list[dict] | None = None) -> dict:
    """``{"items": [...], "count": n, "keys": [node keys], "gateways": [names]}``, kept KEEP_S.
    Each item: kind, label, key (a node's, or "" for a gateway), robot, node, gateway, reason,
    at (ISO 8601, or None), also (the other labels of the same node), said (label, also and reason
    as said() keeps them: view() translates them). ``gateway_views``: the gateways as
    snapshots.gateway_views() gives them, if the caller has them at hand."""
    # (per language: a gateway's reason and a mode's drift come in words made as they are read)
    return cache.get_or_set(f"fleet-attention:{get_language()}", lambda: _read(gateway_views), KEEP_S)


def _read(gateway_views: list[dict] | None) -> dict:
    last = TransitionRecord.objects.filter(node=OuterRef("pk")).order_by("-requested_at", "-id")
    rows = (ManagedNode.objects.filter(robot__enabled=True, last_seen__isnull=False)
            .annotate(last_id=Subquery(last.values("id")[:1]), last_outcome=Subquery(last.values("outcome")[:1]))
            .values_list("key", "name", "robot__name", "robot__gateway__name", "state_label", "alive",
                         "gone_reason", "last_seen", "desired_state", "last_id", "last_outcome",
                         "robot__current_mode__mode__name", "enforcement_stopped", "enforcement_note"))
    found: dict[str, list[tuple[str, Said]]] = {}  # node key -> [(kind, label)]
    nodes: dict[str, tuple] = {}
    in_mode: set[str] = set()  # robots in a mode
    for row in rows:
        key, _, robot, _, state, alive, gone_reason, _, desired, _, outcome, mode, fight, _ = row
        if mode:
            in_mode.add(robot)
        kinds = []
        if outcome in FAILED_OUTCOMES:
            kinds.append((FAILED, plain("")))  # labelled from its record below
        if fight:  # its gateway stopped keeping it in its desired state (ros_gateway/desired_keeper.py)
            kinds.append((FIGHT, said(gettext_noop("another manager keeps changing it"))))
        if alive and desired and state != desired:
            # A mode's states are its nodes' desired states while it is current (lifecycle_site/modes).
            kinds.append((NOT_DESIRED, said(gettext_noop("not as mode %(mode)s says: %(state)s, the mode wants "
                                                         "%(desired)s"), mode=mode, state=state, desired=desired)
                          if mode else said(gettext_noop("not in its desired state: %(state)s, desired state "
                                                         "%(desired)s"), state=state, desired=desired)))
        if not alive:
            if gone_reason == "process_lost":
                kinds.append((PROCESS_LOST, said(gettext_noop("process lost"))))
            else:
                kinds.append((LOST, said(gettext_noop("not answering")) if gone_reason == "unreachable"
                              else said(gettext_noop("lost"))))
        if kinds:
            found[key], nodes[key] = kinds, row
    alerts: dict[str, list[dict]] = {}
    for alert in Alert.objects.filter(status=Alert.Status.FIRING).order_by("-fired_at").values(
            "subject", "rule_name", "summary", "fired_at", "node_name", "robot_name", "gateway_name")[:500]:
        alerts.setdefault(alert["subject"], []).append(alert)
    records = {r["id"]: r for r in TransitionRecord.objects.filter(
        id__in=[nodes[k][9] for k in found if nodes[k][9] is not None]).values(
        "id", "transition_label", "outcome", "error", "requested_at")}
    items = [_node_item(key, nodes[key], found[key], records.get(nodes[key][9]), alerts.pop(key, []))
             for key in found]
    items += _parameter_drift(in_mode, set(found)) if in_mode else []
    items += _diagnostics(alerts)
    for key, fired in alerts.items():  # alerts about nodes that show nothing else
        first = fired[0]
        if first["node_name"]:
            label = said(ALERT_FIRING, rule=first["rule_name"])
            items.append({"kind": ALERT, "label": english(label), "key": key,
                          "robot": first["robot_name"], "node": first["node_name"], "gateway": first["gateway_name"],
                          "reason": first["summary"][:REASON_CHARS], "at": first["fired_at"].isoformat(), "also": [],
                          "said": {"label": label, "also": []}})
    gateways = []
    for view in snapshots.gateway_views() if gateway_views is None else gateway_views:
        if view["robots"] and not view["online"]:
            gateways.append(view["name"])
            what = said(GATEWAY_LABELS.get(view["status"], gettext_noop("gateway offline")))
            fired = alerts.get(view["name"], [])
            also = [said(ALERT_FIRING, rule=a["rule_name"]) for a in fired]
            items.append({"kind": GATEWAY, "label": english(what), "key": "", "robot": ", ".join(view["robots"]),
                          "node": "", "gateway": view["name"], "reason": view["reason_plain"],
                          "at": view["reason_since"], "also": [english(a) for a in also],
                          "said": {"label": what, "also": also}})
    items.sort(key=lambda item: item["at"] or "", reverse=True)  # within a kind, the latest first
    items.sort(key=lambda item: RANK[item["kind"]])
    keys = [item["key"] for item in items if item["key"]]
    return {"items": items, "count": len(items), "keys": keys, "gateways": gateways}


def _parameter_drift(robots: set[str], listed: set[str]) -> list[dict]:
    """Nodes of these robots whose parameters differ from their robot's current mode (their
    state's drift is a desired state not reached, above); one item per node, not listed already."""
    items: dict[str, dict] = {}
    for now_mode in CurrentMode.objects.select_related("robot__gateway", "mode").filter(
            robot__name__in=sorted(robots)[:MODE_ROBOTS]):
        if not any(entry.get("parameters") for entry in now_mode.mode.nodes.values()):
            continue
        for found in drift.differences(now_mode.robot, now_mode):
            if found.kind != "parameter" or found.node_id in listed:
                continue
            label = said(gettext_noop("not as mode %(mode)s says"), mode=now_mode.mode.name)
            item = items.setdefault(found.node_id, {
                "kind": DRIFT, "label": english(label), "key": found.node_id,
                "robot": now_mode.robot.name, "node": found.node, "gateway": now_mode.robot.gateway.name,
                "reason": "", "at": now_mode.since.isoformat(), "also": [], "said": {"label": label, "also": []}})
            item["reason"] = "; ".join(filter(None, (item["reason"], found.words())))[:REASON_CHARS]
    return list(items.values())


def _diagnostics(alerts: dict[str, list[dict]]) -> list[dict]:
    """Diagnostic statuses in ERROR or stale (robots/<r>/diagnostics): one item each, with its message."""
    items = []
    rows = (DiagnosticStatus.objects.filter(robot__enabled=True).filter(Q(stale=True) | Q(level__gte=ERROR))
            .order_by("-level_since").values_list("name", "robot__name", "robot__gateway__name", "level", "stale",
                                                  "message", "level_since", "node")[:DIAGNOSTICS])
    for name, robot, gateway, level, stale, message, since, node in rows:
        fired = alerts.pop(f"{robot}:{name}", [])
        # (ERROR: the diagnostic level's name, as the diagnostics page writes it)
        label = said(gettext_noop("diagnostic stale") if stale or level == STALE else gettext_noop("diagnostic ERROR"))
        reason = plain(message) if not stale else said(gettext_noop("not heard; last said: %(message)s"),
                                                        message=message)
        also = [said(ALERT_FIRING, rule=a["rule_name"]) for a in fired]
        items.append({"kind": DIAGNOSTIC, "label": english(label), "key": "", "robot": robot, "node": "",
                      "status": name, "gateway": gateway, "reason": english(reason)[:REASON_CHARS],
                      "at": since.isoformat(), "also": [english(a) for a in also], "reporter": node,
                      "said": {"label": label, "also": also, "reason": reason}})
    return items


def _failed(record: dict) -> Said:
    """A failed last transition's label: "activate failed", "configure timed out"."""
    with_name, without = FAILED_LABELS.get(record["outcome"], ("", ""))
    if not with_name:  # (not an outcome the strip lists as failed: in English, as it was)
        return plain(f"{record['transition_label'] or 'transition'} "
                     f"{OUTCOME_LABELS.get(record['outcome'], '')}".strip())
    return said(with_name, transition=record["transition_label"]) if record["transition_label"] else said(without)


def _node_item(key: str, row: tuple, kinds: list[tuple[str, Said]], record: dict | None, fired: list[dict]) -> dict:
    _, name, robot, gateway, _, _, _, last_seen, _, _, _, _, fight, fight_note = row
    labels = []
    for kind, label in kinds:
        if kind == FAILED and record is not None:
            label = _failed(record)
        labels.append(label)
    labels += [said(ALERT_FIRING, rule=a["rule_name"]) for a in fired]
    # The last record's words explain a failed transition or a loss; for a node that is up but not
    # in its desired state they may tell of an earlier, ended episode ("its process ended").
    explains = any(kind in (FAILED, LOST, PROCESS_LOST) for kind, _ in kinds)
    reason = ((record or {}).get("error") if explains else "") or (fired[0]["summary"] if fired else "")
    if kinds[0][0] == FIGHT:
        reason, at = fight_note, fight.isoformat()
    elif record is not None:
        at = record["requested_at"].isoformat()
    else:
        at = last_seen.isoformat() if last_seen else None
    return {"kind": kinds[0][0], "label": english(labels[0]), "key": key, "robot": robot, "node": name,
            "gateway": gateway, "reason": reason[:REASON_CHARS], "at": at, "also": [english(a) for a in labels[1:]],
            "said": {"label": labels[0], "also": labels[1:]}}


def view(data: dict) -> dict:
    """What the strip's template takes: the items shown (with their links and their words in the
    active language) and how many more."""
    from urllib.parse import urlencode

    from django.urls import reverse

    fleet = reverse("dashboard:fleet")
    shown = []
    for item in data["items"][:SHOWN]:
        if item.get("status"):
            url = f'{reverse("dashboard:robot-diagnostic", args=[item["robot"]])}?{urlencode({"name": item["status"]})}'
        elif item["key"]:
            url = reverse("dashboard:node", args=[item["key"]])
        else:
            url = f"{fleet}#gateway-{item['gateway']}"
        words = item["said"]
        shown.append({**item, "url": url, "label": say(words["label"]), "also": [say(a) for a in words["also"]]})
        if "reason" in words:
            shown[-1]["reason"] = say(words["reason"])[:REASON_CHARS]
    return {"count": data["count"], "shown": shown, "more": max(0, data["count"] - SHOWN),
            "keys": " ".join(data["keys"]), "gateways": " ".join(data["gateways"])}

"""Applying a robot's mode: one ordered run (its nodes taken down in reverse order, then up in
order, each to the mode's state, parameters set before activation), the mode then current and
its targets the nodes' desired states (automatic recovery brings them back to those)."""
from __future__ import annotations

from django.db import transaction
from django.utils import timezone
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy, pgettext

from lifecycle_site.fleet.models import GroupRun, ManagedNode, Robot
from lifecycle_site.gateway_link.gateway_config import publish_on_commit
from lifecycle_site.modes import definitions, yaml_files
from lifecycle_site.modes.models import CurrentMode, Mode
from lifecycle_site.operations.runs import launch, may_start
from lifecycle_site.refusal import Refusal, shown
from ros_gateway.shared import operations

MODE_RUN = operations.BY_NAME["mode"]
# The refusal of a mode's run to a user without the role (runs.may_start: "%(role)s", the role's name).
APPLYING_NEEDS = gettext_lazy("Applying a mode needs the %(role)s role.")


def mode_of(robot: Robot, name: object) -> Mode:
    """The robot's mode by that name (one of its own, or a template it is among)."""
    mode = Mode.objects.filter(name=name, robots=robot).first() if isinstance(name, str) else None
    if mode is None:
        known = ", ".join(robot.modes.values_list("name", flat=True)) or pgettext("list of modes", "none yet")
        raise Refusal("not_found", _("%(robot)s has no mode %(mode)s (its modes: %(known)s).") % {
            "robot": robot.name, "mode": shown(name), "known": known}, 404)
    return mode


def plan_of(mode: Mode) -> dict:
    return {"mode": mode.name, "targets": mode.targets(), "parameters": mode.parameters()}


def apply_mode(robot: Robot, mode: Mode, *, user, source: str, policy: str = GroupRun.Policy.STOP,
               node_timeout: float = 5.0) -> GroupRun:
    """Start the mode's run; once the gateway took it, the mode is the robot's current one."""
    may_start(robot, MODE_RUN, APPLYING_NEEDS, user, policy)
    problems = definitions.problems(mode.nodes)
    if problems:
        raise Refusal("invalid_mode", _("Mode %(mode)s cannot be applied: %(problems)s") % {
            "mode": mode.name, "problems": " ".join(problems[:3])}, 409)
    if not mode.nodes:
        raise Refusal("invalid_mode", _("Mode %(mode)s names no nodes; an admin defines them first.") % {
            "mode": mode.name}, 409)
    run = launch(robot, MODE_RUN.name, user=user, source=source, policy=policy, node_timeout=node_timeout,
                 nodes=list(mode.nodes), plan=plan_of(mode))
    with transaction.atomic():
        CurrentMode.objects.update_or_create(robot=robot, defaults={
            "mode": mode, "since": run.created or timezone.now(), "run": run, "not_ready_since": None,
            "applied_by": user if getattr(user, "pk", None) else None})
        for state in definitions.STATES:
            names = [name for name, target in mode.targets().items() if target == state]
            ManagedNode.objects.filter(robot=robot, name__in=names).update(desired_state=state)
        publish_on_commit([robot.gateway.name])  # the gateway's recovery reads the desired states
    return run


def import_modes(text: str, robots: list[Robot], user, save: bool) -> dict:
    """A YAML file's modes (this product's export or a system_modes model file) as they would be
    stored for these robots: ``save`` stores them (creating or replacing modes of those names)
    when nothing is wrong; else only the preview. Admins only."""
    if getattr(user, "pk", None) and not user.has_perm("modes.change_mode"):
        raise Refusal("forbidden", _("Defining modes needs the admin role."), 403)
    try:
        modes, problems = yaml_files.read(text)
    except yaml_files.FileRefused as exc:
        raise Refusal("invalid_file", str(exc)) from None
    existing = set(Mode.objects.filter(name__in=[m["name"] for m in modes]).values_list("name", flat=True))
    preview = [{**m, "replaces": m["name"] in existing} for m in modes]
    saved = False
    if save and not problems and modes:
        with transaction.atomic():
            for mode in modes:
                stored, _created = Mode.objects.update_or_create(name=mode["name"], defaults={
                    "nodes": mode["nodes"], "description": mode["description"][:2000],
                    "ready_when": mode["ready_when"],
                    "updated_by": user if getattr(user, "pk", None) else None})
                stored.robots.add(*robots)
        saved = True
    return {"modes": preview, "problems": problems, "saved": saved}

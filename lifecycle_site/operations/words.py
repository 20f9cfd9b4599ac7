"""An operation's words in the reader's language. ros_gateway/shared/operations.py declares them
in English, marked for the catalogue but untranslated (the gateway has no Django); the site asks
here when it shows them: the buttons, a run's title, the help line and the confirmation."""
from __future__ import annotations

from django.utils.translation import gettext

from ros_gateway.shared.operations import Operation


def button(op: Operation) -> str:
    return gettext(op.button)


def title(op: Operation) -> str:
    return gettext(op.title)


def help_line(op: Operation) -> str:
    return gettext(op.help)


def question(op: Operation, robot: str, mode: str = "") -> str:
    """The confirmation with the robot's (and mode's) name in it; ``{nodes}`` is left for the page
    to count (static/js/confirm.js)."""
    return gettext(op.confirm).replace("{robot}", robot).replace("{mode}", mode) if op.confirm else ""


def question_detail(op: Operation) -> str:
    return gettext(op.confirm_detail) if op.confirm_detail else ""

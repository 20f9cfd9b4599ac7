"""Checks shared by the fleet's management commands (add_robot, add_gateway)."""
from __future__ import annotations

from django.core.exceptions import ValidationError
from django.core.management.base import CommandError
from django.db import models


def clean_or_fail(instance: models.Model) -> None:
    """``full_clean()``, its problems as one CommandError line ("name: ...; domain_id: ...")."""
    try:
        instance.full_clean()
    except ValidationError as exc:
        problems = "; ".join(f"{field}: {' '.join(msgs)}" for field, msgs in exc.message_dict.items())
        raise CommandError(problems) from None

"""The stretch of time a timeline shows: the last 15 minutes, hour, day or week
(``?window=hour``), or a range of the operator's own (``?from=...&to=...``, UTC)."""
from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta, timezone
from typing import Mapping
from urllib.parse import urlencode

from django.utils import dateparse
from django.utils import timezone as django_timezone
from django.utils.translation import gettext as _
from django.utils.translation import gettext_lazy, ngettext, pgettext_lazy

WINDOWS: dict[str, timedelta] = {"15min": timedelta(minutes=15), "hour": timedelta(hours=1),
                                 "day": timedelta(days=1), "week": timedelta(weeks=1)}
# Each window's button, after "Last:" (in the active language when the page renders it).
LABELS = {"15min": pgettext_lazy("time window", "15 minutes"), "hour": pgettext_lazy("time window", "hour"),
          "day": pgettext_lazy("time window", "day"), "week": pgettext_lazy("time window", "week")}
# What a page shows instead of a window it cannot show.
SHOWING = {"15min": gettext_lazy("Showing the last 15 minutes."), "hour": gettext_lazy("Showing the last hour."),
           "day": gettext_lazy("Showing the last day."), "week": gettext_lazy("Showing the last week.")}
DEFAULT_WINDOW = "day"
CUSTOM = "custom"
# A range of one's own: long enough to hold a state, short enough that its records are still
# kept (absences and gateway outages are kept 30 days).
MIN_CUSTOM, MAX_CUSTOM = timedelta(minutes=1), timedelta(days=31)


@dataclass(frozen=True)
class Window:
    name: str  # a key of WINDOWS, or CUSTOM
    start: datetime
    end: datetime

    @property
    def seconds(self) -> float:
        return (self.end - self.start).total_seconds()

    @property
    def query(self) -> str:
        """Its part of a page's address, to keep it across links."""
        if self.name != CUSTOM:
            return urlencode({"window": self.name})
        return urlencode({"from": _minute(self.start), "to": _minute(self.end)})


def _minute(moment: datetime) -> str:
    """As a datetime-local field shows it (UTC)."""
    return moment.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S").removesuffix(":00")


def window_of(name: str, now: datetime | None = None) -> Window:
    end = now or django_timezone.now()
    return Window(name, end - WINDOWS[name], end)


def _moment(text: str) -> datetime | None:
    try:
        found = dateparse.parse_datetime(text.strip())
    except ValueError:
        return None
    if found is None:
        return None
    return found.replace(tzinfo=timezone.utc) if found.tzinfo is None else found


class WindowError(ValueError):
    """The query string asks for no window that can be shown; the message says why."""


def parse(query: Mapping[str, str], now: datetime | None = None) -> Window:
    """The window a query string asks for, or WindowError. A range may not end in the future:
    it ends now."""
    now = now or django_timezone.now()
    if query.get("from") or query.get("to"):
        start, end = _moment(query.get("from", "")), _moment(query.get("to", "") or now.isoformat())
        if start is None or end is None:
            raise WindowError(_("Not a date and time: write it like 2026-11-23 14:05 (UTC), or pick it in the "
                                "calendar."))
        end = min(end, now)
        if end - start < MIN_CUSTOM:
            raise WindowError(_("A range must start at least a minute before it ends, and before now."))
        if end - start > MAX_CUSTOM:
            raise WindowError(ngettext("A range may span at most %(days)s day.",
                                       "A range may span at most %(days)s days.", MAX_CUSTOM.days) % {
                "days": MAX_CUSTOM.days})
        return Window(CUSTOM, start, end)
    asked = query.get("window", DEFAULT_WINDOW)
    if asked not in WINDOWS:
        raise WindowError(_("There is no window %(window)s (there are %(windows)s).") % {
            "window": repr(asked[:40]), "windows": ", ".join(WINDOWS)})
    return window_of(asked, now)


def page_window(query: Mapping[str, str], now: datetime | None = None) -> tuple[Window, str]:
    """For a page: the window asked for, or the default one with why."""
    try:
        return parse(query, now), ""
    except WindowError as exc:
        return window_of(DEFAULT_WINDOW, now), f"{exc} {SHOWING[DEFAULT_WINDOW]}"

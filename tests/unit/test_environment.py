"""One parser of environment variables for the site and the gateway (ros_gateway/shared/environment.py):
unset or empty is the default, anything that cannot be meant names the variable and the form it needs."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from ros_gateway.shared import environment as env

ROOT = Path(__file__).resolve().parents[2]


def test_unset_and_empty_are_the_default_and_values_are_read():
    assert env.number("X", 2.5, environ={}) == 2.5 and env.number("X", 2.5, environ={"X": " "}) == 2.5
    assert env.number("X", 2.5, above=0, environ={"X": "0.25"}) == 0.25
    assert env.whole("X", 3, environ={"X": "7"}) == 7
    assert env.flag("X", False, environ={"X": "Yes"}) is True and env.flag("X", True, environ={"X": "off"}) is False
    assert env.items("X", "a,b", environ={"X": " c, ,d "}) == ["c", "d"]
    assert env.megabytes("X", environ={"X": "16"}) == 16 * 1024 * 1024 and env.megabytes("X", environ={}) is None


@pytest.mark.parametrize("call, says", [
    (lambda: env.number("LIFECYCLE_X", 5.0, above=0, environ={"LIFECYCLE_X": "5s"}),
     "LIFECYCLE_X='5s': expected a number of seconds, more than 0 (e.g. 5)."),
    (lambda: env.number("LIFECYCLE_X", 5.0, above=0, environ={"LIFECYCLE_X": "0"}), "more than 0"),
    (lambda: env.number("LIFECYCLE_X", 5.0, environ={"LIFECYCLE_X": "inf"}), "LIFECYCLE_X='inf'"),
    (lambda: env.whole("LIFECYCLE_N", 5, minimum=1, unit="attempts", environ={"LIFECYCLE_N": "2.5"}),
     "LIFECYCLE_N='2.5': expected a whole number of attempts, at least 1 (e.g. 5)."),
    (lambda: env.flag("LIFECYCLE_F", False, environ={"LIFECYCLE_F": "maybe"}),
     "LIFECYCLE_F='maybe': expected true or false"),
    (lambda: env.megabytes("LIFECYCLE_M", environ={"LIFECYCLE_M": "-3"}),
     "LIFECYCLE_M='-3': expected a number of MB, more than 0 and at most 1e+06 (e.g. 16)."),
])
def test_a_value_that_cannot_be_meant_names_the_variable_and_the_form(call, says):
    with pytest.raises(env.SettingError) as refused:
        call()
    assert says in str(refused.value)


def test_the_site_stops_at_start_naming_the_variable():
    environ = {**os.environ, "DJANGO_SETTINGS_MODULE": "lifecycle_site.settings", "LIFECYCLE_ALERT_WORKERS": "two"}
    done = subprocess.run([sys.executable, "-c", "import django; django.setup()"], cwd=ROOT, env=environ,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert "LIFECYCLE_ALERT_WORKERS='two': expected a whole number of workers" in done.stderr


def test_pages_show_utc_as_they_say_whatever_tz_says():
    """An Edge device set to Europe/Berlin (site.timeZone: TZ): the pages' "When (UTC)" columns,
    and the dates Django's |date filter writes beside them, are UTC all the same."""
    environ = {**os.environ, "DJANGO_SETTINGS_MODULE": "lifecycle_site.settings", "TZ": "Europe/Berlin"}
    script = ("import django; django.setup(); from datetime import datetime, timezone; "
              "from django.template import Context, Template; "
              "print(Template('{{ t|date:\"Y-m-d H:i\" }}').render(Context("
              "{'t': datetime(2026, 7, 1, 12, 0, tzinfo=timezone.utc)})))")
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env=environ, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "2026-07-01 12:00"  # not 14:00, Berlin's summer time

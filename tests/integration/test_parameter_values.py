"""Parameter values that cannot be set or stored (NaN, infinities) on a real joy_to_vel node
through the real gateway: refused before anything is sent, and every value that is sent is
in the audit log even when recording another one fails."""
from __future__ import annotations

import json
import math
import time

import pytest
import redis
from django.conf import settings
from django.core.files.uploadedfile import SimpleUploadedFile

from lifecycle_site.audit.models import ParameterRecord
from ros_gateway.shared import protocol
from tests import stack
from tests.integration.conftest import register, wait_node

ROBOT = "it-params"
KEY = f"{ROBOT}.joy_to_vel"
DEFAULT_DEADMAN = 4  # ros_gateway/demo/teleop.py


@pytest.fixture(scope="module")
def joy(gateway):
    register(ROBOT, stack.domain(12))
    process = stack.start_robot("params-joy", stack.domain(12), "joy_to_vel")
    wait_node(None, KEY, alive=True, state="unconfigured")
    yield process
    process.stop()


def node_values(api) -> dict:
    """The values as the node itself reports them now (read through the gateway)."""
    response = api.get(f"/api/v1/nodes/{KEY}/parameters")
    assert response.status_code == 200, response.json()
    return {p["name"]: p["value"] for p in response.json()["parameters"]}


def records(name: str | None = None):
    found = ParameterRecord.objects.filter(node__key=KEY)
    return found.filter(name=name) if name else found


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_numbers_are_refused_before_anything_is_sent(api, joy, literal):
    before = node_values(api)
    assert before["deadman_button"] == DEFAULT_DEADMAN
    body = '{"scale_linear": %s, "deadman_button": 7}' % literal
    response = api.patch(f"/api/v1/nodes/{KEY}/parameters", body, content_type="application/json")
    assert response.status_code == 400, response.content
    error = response.json()["error"]
    assert error["code"] == "non_finite_number"
    assert (error["value"], error["path"]) == (literal, ["scale_linear"])
    assert f"{literal} at scale_linear is not a finite number" in error["message"]
    assert "Nothing was sent" in error["message"]
    assert node_values(api) == before
    assert not records().exists()


def test_dashboard_form_refuses_non_finite_numbers(api, joy):
    before = node_values(api)
    for raw in ("nan", "inf", "-Infinity", "1e999"):
        page = api.post(f"/nodes/{KEY}/parameters", {"seen:scale_linear": "1", "value:scale_linear": raw})
        assert page.status_code == 200
        assert f"not set: {raw} is not a finite number" in page.content.decode()
    assert node_values(api) == before
    assert not records().exists()


def test_parameter_file_with_nan_and_inf_applies_only_the_finite_values(api, joy):
    before = node_values(api)
    text = "/joy_to_vel:\n  ros__parameters:\n    scale_linear: .nan\n    scale_angular: -.inf\n    deadman_button: 6\n"
    upload = SimpleUploadedFile("joy.yaml", text.encode(), content_type="application/x-yaml")
    page = api.post(f"/nodes/{KEY}/parameters/import", {"file": upload}).content.decode()
    assert "cannot be set: nan, not a finite number" in page
    assert "cannot be set: -inf, not a finite number" in page
    assert 'name="values" value="{&quot;deadman_button&quot;: 6}"' in page  # what "Apply" sends

    # A preview altered to carry NaN again is refused whole.
    page = api.post(f"/nodes/{KEY}/parameters/apply",
                    {"values": '{"deadman_button": 6, "scale_linear": NaN}'}).content.decode()
    assert "Nothing was sent: NaN at scale_linear is not a finite number" in page
    assert node_values(api) == before
    assert not records().exists()

    page = api.post(f"/nodes/{KEY}/parameters/apply", {"values": '{"deadman_button": 6}'}).content.decode()
    assert "All changes accepted by the node." in page
    assert node_values(api)["deadman_button"] == 6
    assert records("deadman_button").get().new_value == 6
    assert not records("scale_linear").exists() and not records("scale_angular").exists()


def test_a_name_that_cannot_be_stored_as_it_is_is_recorded_and_loses_no_other_record(api, joy):
    """A name with a lone UTF-16 surrogate (valid JSON) cannot be stored in SQLite as it is: its
    record keeps it with U+FFFD in its place, and the value sent with it is recorded and answered."""
    before = node_values(api)["deadman_button"]
    wanted = 9 if before != 9 else 8
    count = records().count()
    body = '{"\\ud800": 1, "deadman_button": %d}' % wanted
    response = api.patch(f"/api/v1/nodes/{KEY}/parameters", body, content_type="application/json")
    assert response.status_code == 422, response.content
    results = response.json()["error"]["results"]
    assert [(r["name"], r["successful"]) for r in results] == [("\ud800", False), ("deadman_button", True)]
    assert "has no parameter" in results[0]["reason"]
    assert node_values(api)["deadman_button"] == wanted
    record = records("deadman_button").order_by("-id").first()
    assert (record.old_value, record.new_value, record.outcome) == (before, wanted, "succeeded")
    assert records().count() == count + 2
    last = {r.name.strip("\ufffd") or "\ufffd": r.outcome for r in records().order_by("-id")[:2]}
    assert last == {"\ufffd": "rejected", "deadman_button": "succeeded"}


def test_gateway_records_a_non_finite_value_as_text_and_every_other_value(api, joy):
    """Defence in depth: a NaN that reaches the gateway (not through the API, which refuses
    it) is refused by the check, recorded as "nan", and the value sent with it is recorded."""
    before = node_values(api)
    wanted = 3 if before["deadman_button"] != 3 else 2
    # The site never sends NaN (its encoder refuses it): written to the queue by hand, as JSON
    # with a NaN literal, the way a careless client would.
    prefix = settings.CHANNEL_LAYERS["default"]["CONFIG"]["prefix"]
    client = redis.Redis.from_url(settings.REDIS_URL, socket_timeout=30)
    command = {"command": protocol.SET_PARAMETERS, "request_id": "nan-by-hand", "deadline": time.time() + 20,
               "robot": ROBOT, "node": "/joy_to_vel", "values": {"scale_linear": math.nan, "deadman_button": wanted}}
    client.lpush(protocol.command_queue(prefix, "local"), json.dumps(command))
    reply = json.loads(client.blpop([protocol.reply_key(prefix, "local", "nan-by-hand")], timeout=20)[1])
    results = {r["name"]: r for r in reply["results"]}
    assert not results["scale_linear"]["successful"] and "must be a number" in results["scale_linear"]["reason"]
    assert results["deadman_button"]["successful"]
    after = node_values(api)
    assert (after["deadman_button"], after["scale_linear"]) == (wanted, before["scale_linear"])
    # Called past the site's request path: the ingest process stores the records from the stream.
    refused = stack.wait_for(lambda: records("scale_linear").first(), 10, "the refused value's record")
    assert (refused.outcome, refused.old_value, refused.new_value) == ("rejected", before["scale_linear"], "nan")
    stack.wait_for(lambda: records("deadman_button").filter(id__gt=refused.id, new_value=wanted).exists(), 10,
                   "the record of the value sent with it")


@pytest.mark.parametrize("name, value, says", [
    ("deadman_button", "9" * 400, "64-bit integer"),
    ("deadman_button", str(2**63), "64-bit integer"),
    ("scale_linear", "9" * 400, "too large for a double"),
])
def test_numbers_too_large_for_the_parameter_type_are_refused_with_why(api, joy, name, value, says):
    before = node_values(api)
    response = api.patch(f"/api/v1/nodes/{KEY}/parameters", '{"%s": %s}' % (name, value),
                         content_type="application/json")
    assert 400 <= response.status_code < 500, response.content
    assert says in json.dumps(response.json()), response.json()
    assert node_values(api) == before


def test_a_value_refused_on_the_node_page_stays_in_its_field_with_the_reason(api, joy):
    """Issue 26, item 6: the form showed the node's current value again after a refusal, so the
    operator had to type the refused value again to correct it."""
    before = node_values(api)["scale_linear"]
    page = api.post(f"/nodes/{KEY}/parameters", {"seen:scale_linear": "1", "value:scale_linear": "5.0"})
    text = page.content.decode()
    assert "not set: scale_linear must be between 0 and 2" in text
    field = text.split('name="value:scale_linear"', 1)[1].split(">", 1)[0]
    assert 'value="5.0"' in field, field
    assert node_values(api)["scale_linear"] == before

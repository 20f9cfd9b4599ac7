"""NaN, Infinity, -Infinity and 1e999 (which Python's json accepts) are refused by the API's
body parser and the dashboard before anything is sent; audit values are always storable."""
from __future__ import annotations

import json
import math

import pytest

from lifecycle_site.api.auth import NonFiniteNumber, loads_finite
from lifecycle_site.audit.models import ParameterRecord, TransitionRecord
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.fleet.param_files import diff, load
from ros_gateway.shared import param_types as pt
from ros_gateway.shared import state_machine as sm


@pytest.mark.parametrize(
    "text, literal, path",
    [
        ('{"scale_linear": NaN, "deadman_button": 7}', "NaN", ("scale_linear",)),
        ('{"scale_linear": Infinity}', "Infinity", ("scale_linear",)),
        ('{"scale_linear": -Infinity}', "-Infinity", ("scale_linear",)),
        ('{"scale_linear": 1e999}', "1e999", ("scale_linear",)),
        ('{"scale_linear": -1.5E+400}', "-1.5E+400", ("scale_linear",)),
        ('{"gains": [0.5, [1.0, NaN]]}', "NaN", ("gains", 1, 1)),
        ('[{"a": {"b": [Infinity]}}]', "Infinity", (0, "a", "b", 0)),
        ("NaN", "NaN", ()),
    ],
)
def test_parser_refuses_non_finite_numbers_and_names_them(text, literal, path):
    with pytest.raises(NonFiniteNumber) as refused:
        loads_finite(text)
    assert (refused.value.literal, refused.value.path) == (literal, path)
    assert str(refused.value).startswith(f"{literal}{' at ' if path else ' '}")
    assert "not a finite number" in str(refused.value)


def test_parser_keeps_everything_else_as_json_loads_does():
    text = ('{"big": 1.7976931348623157e308, "tiny": 5e-324, "int": 100000000000000000000000, '
            '"text": "NaN", "l": [1, 2.5]}')
    assert loads_finite(text) == json.loads(text)
    with pytest.raises(ValueError):
        loads_finite('{"a": ')


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="unit-agv", domain_id=99)
    return ManagedNode.objects.create(
        robot=robot, name="/joy_to_vel", alive=True, state_id=sm.UNCONFIGURED, state_label="unconfigured"
    )


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_api_refuses_them_with_the_error_shape_without_calling_the_gateway(operator_client, node, literal):
    # No gateway runs here: a body that got past the parser would be answered 503 gateway_offline.
    response = operator_client.patch(f"/api/v1/nodes/{node.key}/parameters",
                                     '{"scale_linear": %s, "deadman_button": 7}' % literal,
                                     content_type="application/json")
    assert response.status_code == 400
    assert response.json() == {"error": {
        "code": "non_finite_number",
        "message": f"Nothing was sent: {literal} at scale_linear is not a finite number (NaN, Infinity, "
                   "-Infinity and numbers beyond ±1.8e308, such as 1e999, cannot be used).",
        "value": literal, "path": ["scale_linear"]}}
    response = operator_client.post(f"/api/v1/nodes/{node.key}/transition",
                                    '{"transition": "configure", "timeout": %s}' % literal,
                                    content_type="application/json")
    assert response.status_code == 400 and response.json()["error"]["code"] == "non_finite_number"
    assert not ParameterRecord.objects.exists() and not TransitionRecord.objects.exists()


def test_storable_turns_non_finite_floats_into_text_anywhere():
    value = {"a": [1.0, math.nan, [math.inf]], "b": -math.inf, "c": "x", "d": 3}
    assert pt.storable(value) == {"a": [1.0, "nan", ["inf"]], "b": "-inf", "c": "x", "d": 3}
    assert pt.non_finite(value) == (("a", 1), value["a"][1])
    assert pt.non_finite(pt.storable(value)) is None
    json.dumps(pt.storable(value), allow_nan=False)  # what the JSON columns need


def test_parameter_file_values_that_are_not_finite_are_shown_not_applied():
    current = [{"name": "scale_linear", "value": 0.5}, {"name": "gains", "value": [1.0, 2.0]},
               {"name": "deadman_button", "value": 4}]
    wanted = load("/joy_to_vel:\n  ros__parameters:\n    scale_linear: .nan\n    gains: [1.0, .inf]\n"
                  "    deadman_button: 6\n", "/joy_to_vel")
    notes = {c["name"]: c["note"] for c in diff(current, wanted)}
    assert notes == {"scale_linear": "cannot be set: nan, not a finite number",
                     "gains": "cannot be set: item 1 is inf, not a finite number", "deadman_button": ""}

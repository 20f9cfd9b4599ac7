"""Parameter files from operators: work bounded by the file, not by how it is nested.

PyYAML's pure-Python scanner reads ahead over every '[' that may start a key, in time
quadratic in their depth: a 10 KB file of 5,000 '[' took 9.5 s of CPU to refuse."""
from __future__ import annotations

import time

import pytest
import yaml
from django.core.files.uploadedfile import SimpleUploadedFile

from lifecycle_site.fleet import param_files
from lifecycle_site.fleet.models import ManagedNode, Robot
from lifecycle_site.fleet.param_files import MAX_NESTING, ParameterFileError, load
from ros_gateway.shared import state_machine as sm

HEAD = "/joy_to_vel:\n  ros__parameters:\n    scale: "
# Well under a second: a refusal the operator gets at once, on a slow device too.
CPU_BOUND = 0.5


@pytest.fixture
def node(db) -> ManagedNode:
    robot = Robot.objects.create(name="unit-agv", domain_id=99)
    return ManagedNode.objects.create(
        robot=robot, name="/joy_to_vel", alive=True, state_id=sm.UNCONFIGURED, state_label="unconfigured"
    )


def upload(client, node: ManagedNode, text: str) -> tuple[str, float]:
    """POST the file to the import page (no gateway runs: a file that got past the parser would
    be answered with the gateway's error); the page's text and the CPU time it took."""
    started = time.process_time()
    response = client.post(f"/nodes/{node.key}/parameters/import",
                           {"file": SimpleUploadedFile("p.yaml", text.encode())})
    spent = time.process_time() - started
    assert response.status_code == 200
    return response.content.decode(), spent


def test_a_deeply_nested_file_is_refused_at_once_naming_the_limit(operator_client, node):
    text = HEAD + "[" * 5000 + "\n"  # 10 KB
    page, spent = upload(operator_client, node, text)
    assert spent < CPU_BOUND, f"{spent:.2f} s of CPU"
    assert f"p.yaml: lists or mappings nested more than {MAX_NESTING} levels deep (line 3)" in page


@pytest.mark.parametrize("literal", [
    "1" * 5000,  # Python refuses int() of more than 4,300 digits (ValueError: a 500)
    "1" + ":1" * 120_000,  # YAML 1.1 base 60: a 240 KB integer took seconds to compute
], ids=["decimal", "base60"])
def test_an_overlong_integer_is_refused_not_computed(operator_client, node, literal):
    page, spent = upload(operator_client, node, HEAD + literal + "\n")
    assert spent < CPU_BOUND, f"{spent:.2f} s of CPU"
    assert "an integer of more than 100 characters (line 3); ROS integers are 64-bit" in page


def nested(levels: int, shape: str) -> str:
    """A file whose deepest value is `levels` lists or mappings deep (the file's own mapping,
    the node's, ros__parameters' and the value's count)."""
    inner = levels - 3
    if shape == "flow":
        value = "{a: " * (inner - 1) + "[1]" + "}" * (inner - 1)
    elif shape == "sequences":
        value = "\n      " + "- " * inner + "1"
    else:  # block mappings, by indentation
        value = "".join("\n" + "  " * (3 + i) + "a:" for i in range(inner)) + " 1"
    return HEAD + value + "\n"


@pytest.fixture(params=["python", "libyaml"])
def loader(request, monkeypatch):
    """Both loaders: libyaml's where the wheel has it (the product's case), PyYAML's own otherwise."""
    if request.param == "libyaml" and not yaml.__with_libyaml__:
        pytest.fail("PyYAML without libyaml: the product would use the Python loader")
    chosen = param_files._CLoader if request.param == "libyaml" else param_files._PythonLoader
    monkeypatch.setattr(param_files, "LOADER", chosen)
    return chosen


@pytest.mark.parametrize("shape", ["flow", "sequences", "mappings"])
def test_the_limit_holds_for_every_way_of_nesting_with_either_loader(loader, shape):
    wanted = load(nested(MAX_NESTING, shape), "/joy_to_vel")
    assert len(wanted) == 1 and next(iter(wanted)).startswith("scale")  # mappings become dotted names
    with pytest.raises(ParameterFileError, match=f"nested more than {MAX_NESTING} levels deep"):
        load(nested(MAX_NESTING + 1, shape), "/joy_to_vel")
    for depth in (5000, 50_000):
        text = HEAD + "[" * depth if shape == "flow" else "- " * depth + "1"
        started = time.process_time()
        with pytest.raises(ParameterFileError, match="nested more than"):
            load(text, "/joy_to_vel")
        assert time.process_time() - started < CPU_BOUND / 10


def test_an_ordinary_file_still_loads_with_either_loader(loader):
    text = HEAD + "0.5\n    gains: [1.0, 2.0]\n    limits:\n      max: 9_223_372_036_854_775_807\n      min: -0x10\n"
    assert load(text, "/joy_to_vel") == {"scale": 0.5, "gains": [1.0, 2.0], "limits.max": 2 ** 63 - 1,
                                         "limits.min": -16}


def listed(name: str, value, kind: str, low=None, high=None, read_only: bool = False) -> dict:
    """One parameter as the gateway lists it (ros_gateway/parameters.py)."""
    ranges = [{"from_value": low, "to_value": high, "step": 0}] if low is not None else []
    return {"name": name, "value": value, "type": kind, "read_only": read_only, "dynamic_typing": False,
            "integer_range": ranges if kind == "integer" else [],
            "floating_point_range": ranges if kind == "double" else []}


def test_the_preview_makes_every_check_the_gateway_makes_before_it_sends():
    """Issue 26: the preview let `publish_rate_hz: 99` through (range 1-50); Apply then set
    `scale_linear` and the gateway refused the other: half a file applied."""
    current = [listed("scale_linear", 0.5, "double", 0.0, 2.0), listed("publish_rate_hz", 10.0, "double", 1.0, 50.0),
               listed("deadman_button", 4, "integer", 0, 11), listed("frame_id", "base", "string", read_only=True),
               listed("axis_linear", 1, "integer", 0, 7)]
    wanted = load("/joy_to_vel:\n  ros__parameters:\n    scale_linear: 0.8\n    publish_rate_hz: 99\n"
                  "    deadman_button: 2.5\n    frame_id: odom\n    no_such: 1\n    axis_linear: 1.0\n"
                  "    axis_angular: 3\n", "/joy_to_vel")
    changes = {c["name"]: c for c in param_files.diff(current, wanted)}
    assert {name: c["note"] for name, c in changes.items()} == {
        "scale_linear": "",
        "publish_rate_hz": "must be between 1 and 50",  # the descriptor's range
        "deadman_button": "must be a whole number",  # its type
        "frame_id": "is read-only",
        "no_such": "the node has no such parameter",
        "axis_angular": "the node has no such parameter",
    }  # axis_linear: 1.0 is its current value, no change
    assert changes["scale_linear"]["value"] == 0.8
    # An integer for a double is sent as the double the node takes.
    changes = param_files.diff(current, {"publish_rate_hz": 20})
    assert changes[0]["note"] == "" and changes[0]["value"] == 20.0 and isinstance(changes[0]["value"], float)

"""Which parameters get a select on the node page: bools, and those whose descriptor names a
fixed list of values in additional_constraints (ROS has no field for it)."""
from __future__ import annotations

import pytest

from lifecycle_site.dashboard.parameter_views import choices


def entry(kind: str, constraints: str = "") -> dict:
    return {"type": kind, "additional_constraints": constraints}


@pytest.mark.parametrize(("kind", "constraints", "expected"), [
    ("bool", "", ["true", "false"]),
    ("string", "one of: none, fail_configure, crash", ["none", "fail_configure", "crash"]),
    ("string", "Allowed values: 'low' | 'high'.", ["low", "high"]),
    ("string", "[rgb8, mono8]", ["rgb8", "mono8"]),
    ("integer", "one of: 1, 2, 4", ["1", "2", "4"]),
    ("double", "choices: 0.5, 1", ["0.5", "1.0"]),
])
def test_a_fixed_list_becomes_choices(kind, constraints, expected):
    assert choices(entry(kind, constraints)) == expected


@pytest.mark.parametrize(("kind", "constraints"), [
    ("string", ""),
    ("string", "must be a TF frame"),
    ("string", "one of the camera modes, see the manual"),  # prose, not a list
    ("string", "one of: only"),  # one value is no choice
    ("integer", "one of: 1, two"),  # not all of its type
    ("string", "one of: " + ", ".join(f"v{i}" for i in range(51))),  # too many for a select
    ("string_array", "one of: a, b"),
    ("string", "one of: " + "a" * 600 + ", b"),
])
def test_anything_else_stays_a_free_field(kind, constraints):
    assert choices(entry(kind, constraints)) is None

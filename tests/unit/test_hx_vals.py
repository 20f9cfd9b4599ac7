"""htmx request values (hx-vals) are JSON built from names the robots report: whatever a
transition label or a node name holds, a button sends exactly that value and nothing else
(a label must not turn its button into another transition, skipping that one's confirmation)."""
from __future__ import annotations

import json
from html.parser import HTMLParser

import pytest
from django.template.loader import render_to_string
from django.test import Client

from lifecycle_site.dashboard import snapshots
from ros_gateway.shared import protocol
from ros_gateway.shared import state_machine as sm

HOSTILE = [
    '", "transition": "shutdown',
    '\\", "transition": "shutdown',
    "' onclick='alert(1)",
    "&quot;, &#34;transition&#34;: &quot;shutdown",
    "</button><script>alert(1)</script>",
    "{{ t.label }} \u2028 \u00e9 \\u0022",
]


class _Buttons(HTMLParser):
    """Every element's hx-vals (or another attribute) parsed as JSON, as a browser reads the
    attribute (character references decoded)."""

    def __init__(self, attribute: str = "hx-vals") -> None:
        super().__init__()
        self.attribute = attribute
        self.vals: list[dict] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        for name, value in attrs:
            if name == self.attribute:
                self.vals.append(json.loads(value or ""))


def hx_vals(html: str) -> list[dict]:
    parser = _Buttons()
    parser.feed(html)
    parser.close()
    return parser.vals


def node(name: str = "/lidar", alive: bool = True, label: str | None = None) -> dict:
    payload = protocol.node_payload(key="agv-1.lidar", robot="agv-1", name=name, state_id=sm.UNCONFIGURED,
                                    alive=alive, last_seen="2026-01-01T10:00:00+00:00" if alive else None)
    if label is not None:
        payload["transitions"] = [{"id": 1, "label": label}]
    return payload


@pytest.mark.parametrize("text", HOSTILE)
def test_a_fleet_rows_transition_button_sends_exactly_its_label(text: str):
    row = render_to_string("dashboard/_node_row.html",
                           {"nodes": [snapshots.fleet_row(node(label=text))], "oob": "", "can_operate": True})
    assert hx_vals(row) == [{"transition": text}]


@pytest.mark.parametrize("text", HOSTILE)
def test_the_node_pages_transition_button_sends_exactly_its_label(text: str):
    panel = render_to_string("dashboard/_node_state.html",
                             {**snapshots.state_panel(node(label=text)), "can_operate": True})
    assert hx_vals(panel) == [{"transition": text}]


@pytest.mark.parametrize("text", HOSTILE)
def test_the_unwatch_button_sends_exactly_the_nodes_name(text: str):
    waiting = snapshots.fleet_row(node(name=text, alive=False))
    row = render_to_string("dashboard/_node_row.html", {"nodes": [waiting], "oob": "", "can_operate": True})
    assert hx_vals(row) == [{"name": text, "action": "unwatch"}]


def test_the_buttons_of_ordinary_names_are_unchanged():
    row = render_to_string("dashboard/_node_row.html",
                           {"nodes": [snapshots.fleet_row(node())], "oob": "", "can_operate": True})
    assert hx_vals(row) == [{"transition": "configure"}, {"transition": "shutdown"}]


def test_the_pages_csrf_header_is_json_that_passes_the_check(db):
    client = Client(enforce_csrf_checks=True)
    page = client.get("/login/").content.decode()
    parser = _Buttons("hx-headers")
    parser.feed(page)
    [headers] = parser.vals
    assert list(headers) == ["X-CSRFToken"]
    answer = client.post("/login/", {"username": "nobody", "password": "x"}, headers=headers)
    assert answer.status_code == 200  # the form again (wrong password), not a 403 CSRF refusal

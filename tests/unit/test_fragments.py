"""Live fragments: sockets that would render the same update share one rendering, briefly."""
from __future__ import annotations

from lifecycle_site.dashboard import fragments


def test_the_same_update_for_the_same_kind_of_page_is_rendered_once(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(fragments.time, "monotonic", lambda: clock[0])
    renders: list[str] = []

    def render(text: str):
        return lambda: renders.append(text) or f"<tr>{text}</tr>"

    node = {"id": "agv-1.lidar", "state": {"id": 3, "label": "active"}}
    for _ in range(25):  # 25 fleet pages of operators
        assert fragments.rendered(("row", "", True, node), render("operator")) == "<tr>operator</tr>"
    fragments.rendered(("row", "", False, node), render("viewer"))  # another role: its own
    fragments.rendered(("row", "/lifecycle", True, node), render("prefixed"))  # another prefix
    assert renders == ["operator", "viewer", "prefixed"]
    moved = {**node, "state": {"id": 2, "label": "inactive"}}
    fragments.rendered(("row", "", True, moved), render("moved on"))
    clock[0] += fragments.KEEP_S + 0.01  # kept a moment only: a panel carries its render time
    fragments.rendered(("row", "", True, node), render("later"))
    assert renders == ["operator", "viewer", "prefixed", "moved on", "later"]


def test_what_is_kept_is_bounded(monkeypatch):
    monkeypatch.setattr(fragments, "SIZE", 3)
    for n in range(10):
        fragments.rendered(("row", n), lambda n=n: str(n))
    assert len(fragments._kept) == 3

"""Dependencies run one way: the gateway never imports the site, the site imports only the
shared vocabulary of the gateway, and the vocabulary imports neither rclpy nor Django."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def imports(path: Path) -> set[str]:
    """Every module a file imports (absolute names; relative imports are not used here)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def sources(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def test_nothing_under_ros_gateway_imports_the_site():
    offenders = {
        str(path.relative_to(ROOT)): sorted(name for name in imports(path) if name.startswith("lifecycle_site"))
        for path in sources("ros_gateway")
    }
    assert {path: names for path, names in offenders.items() if names} == {}


def test_the_gateway_uses_no_database():
    database = ("django.db", "django.contrib.auth", "asgiref.sync")
    offenders = {
        str(path.relative_to(ROOT)): sorted(n for n in imports(path) if n.startswith(database))
        for path in sources("ros_gateway")
    }
    assert {path: names for path, names in offenders.items() if names} == {}


def test_the_site_imports_only_the_shared_vocabulary_of_the_gateway():
    offenders = {}
    for path in sources("lifecycle_site"):
        names = sorted(
            name for name in imports(path)
            if name.startswith("ros_gateway") and not name.startswith("ros_gateway.shared")
        )
        if names:
            offenders[str(path.relative_to(ROOT))] = names
    assert offenders == {}


def test_the_shared_vocabulary_needs_neither_rclpy_nor_django():
    for path in sources("ros_gateway/shared"):
        heavy = sorted(n for n in imports(path) if n.split(".")[0] in ("rclpy", "django", "channels", "redis"))
        assert heavy == [], f"{path.name} imports {heavy}"

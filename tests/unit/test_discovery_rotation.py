"""Looking for restarted processes costs one graph query per node: the discovery pass checks
nodes in turn within a time budget, so a big robot never stalls the gateway's event loop, and
every node's turn still comes."""
from __future__ import annotations

from types import SimpleNamespace

from ros_gateway import discovery as disc
from ros_gateway.parts import Core
from ros_gateway.registry import LiveNode, NodeRegistry, RobotInfo, StateChanges


class SlowChecks(disc.Discovery):
    def __init__(self, cost_s: float) -> None:
        core = Core(NodeRegistry(StateChanges()), {}, outbox=None, relay=None, service_timeout=1.0)
        super().__init__(core, lambda domain_id: None, forget_parameters=lambda key: None)
        self.cost_s, self.checked = cost_s, []

    def _check_incarnation(self, domain, node) -> None:
        self.checked.append(node.name)
        self.clock += self.cost_s


def run_passes(monkeypatch, cost_s: float, nodes: int, passes: int) -> list[list[str]]:
    discovery = SlowChecks(cost_s)
    discovery.clock = 0.0
    monkeypatch.setattr(disc.time, "monotonic", lambda: discovery.clock)
    robot = RobotInfo(1, "agv", 5, "", False)
    live = [LiveNode(robot, f"/n{i:03d}", alive=True) for i in range(nodes)]
    domain = SimpleNamespace(domain_id=5)
    per_pass = []
    for _ in range(passes):
        discovery.checked = []
        discovery._check_incarnations(domain, list(reversed(live)), discovery.clock + disc.INCARNATION_BUDGET_S)
        per_pass.append(discovery.checked)
    return per_pass


def test_a_few_nodes_are_all_checked_every_pass(monkeypatch):
    per_pass = run_passes(monkeypatch, cost_s=0.0002, nodes=5, passes=3)
    assert all(sorted(names) == [f"/n{i:03d}" for i in range(5)] for names in per_pass)


def test_many_nodes_are_checked_in_turn_within_the_budget(monkeypatch):
    per_pass = run_passes(monkeypatch, cost_s=0.001, nodes=30, passes=8)
    budget_checks = round(disc.INCARNATION_BUDGET_S / 0.001)
    assert all(len(names) == budget_checks for names in per_pass)
    seen = [name for names in per_pass for name in names]
    # In name order, each node once, wrapping round: after 30 checks the first comes again.
    assert seen[:30] == [f"/n{i:03d}" for i in range(30)] and seen[30] == "/n000"


def test_a_slow_check_still_lets_one_node_a_pass_have_its_turn(monkeypatch):
    per_pass = run_passes(monkeypatch, cost_s=1.0, nodes=3, passes=4)
    assert per_pass == [["/n000"], ["/n001"], ["/n002"], ["/n000"]]

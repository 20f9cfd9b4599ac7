"""Plain-data views of fleet models, shared by the API and the live pages."""
from __future__ import annotations

from lifecycle_site.fleet.models import ManagedNode
from ros_gateway.shared.protocol import node_payload


def node_dict(node: ManagedNode) -> dict:
    """Same shape as the gateway's live updates; ``node.robot`` should be select_related."""
    return node_payload(
        key=node.key,
        robot=node.robot.name,
        name=node.name,
        state_id=node.state_id,
        alive=node.alive,
        gone_reason=node.gone_reason,
        last_seen=node.last_seen.isoformat() if node.last_seen else None,
        process_status=node.process_status,
        process_since=node.process_since.isoformat() if node.process_since else None,
    )

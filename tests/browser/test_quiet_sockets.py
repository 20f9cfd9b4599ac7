"""Live-update sockets of fleet and node pages stay open while nothing happens on the fleet.

Every consumer waits on the channel layer, which blocks in Redis (BZPOPMIN) for 5 s at a
time; when the Redis client's read timeout is not longer than that, one consumer per 5 s dies
with a TimeoutError and daphne closes its socket with 1011. The sockets here carry a session
from the login form, as a browser's do (a WebSocket client rather than Chromium, so that every
close and its code is seen: the page itself would just reconnect).
"""
from __future__ import annotations

import asyncio
from urllib.parse import urlparse

from tests.benchmarks.quiet import hold_sockets, summary
from tests.benchmarks.web import Http
from tests.browser.conftest import PASSWORD, ROBOT

WINDOW_S = 15.0  # three blocking pops in a row; with the old client one socket closed every 5 s
FLEET_SOCKETS = 10


def test_sockets_stay_open_on_a_quiet_fleet(site, robot, operator):
    address = urlparse(site)
    web = Http(address.hostname, address.port)
    web.login(operator.username, PASSWORD)
    nodes = [f"/ws/nodes/{ROBOT}.{node}/" for node in ("lidar_driver", "camera_driver")]
    paths = ["/ws/fleet/"] * FLEET_SOCKETS + nodes
    try:
        outcomes = asyncio.run(hold_sockets(web, paths, WINDOW_S))
    finally:
        web.close()
    assert not any(o.close_code is not None for o in outcomes), summary(outcomes)
    assert len(outcomes) == len(paths)

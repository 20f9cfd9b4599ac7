"""The site's grants (lifecycle_site/gateway_link/attribution.py): a fact signed before an upgrade
(waiting in Redis while the site was upgraded, or late after a reply timed out) still verifies
after it, or its record would lose who asked."""
from __future__ import annotations

from lifecycle_site.gateway_link import attribution

KEY = "a fixed key of this test, not a secret"


def test_a_grant_is_what_the_release_before_the_fleet_split_made():
    # Made by c3463f6 (lifecycle_site/fleet/attribution.py): salt, message layout and digest unchanged.
    assert attribution.grant("req-1", 7, "api", "agv-1", "/lidar", "transition:activate",
                             secret=KEY) == "bed6a200348df29684c4e36162814b320839baa3"

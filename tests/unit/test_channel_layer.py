"""The channel layer's Redis connections, as the settings make them, outlast its blocking pop.

A consumer waits in a BZPOPMIN of ``brpop_timeout`` seconds; a client read timeout that is
not clearly longer ends that wait with a TimeoutError, which kills the consumer (daphne then
closes its WebSocket with 1011). The connections are built by channels-redis and redis-py
themselves, so whatever either version defaults to is what is checked.
"""
from __future__ import annotations

import math

from channels_redis.utils import create_pool
from django.conf import settings
from django.utils.module_loading import import_string

MARGIN_S = 1.0  # Redis answers a timed-out pop on its next event-loop turn, not to the ms


def test_redis_read_timeout_outlasts_the_blocking_pop():
    config = settings.CHANNEL_LAYERS["default"]
    layer = import_string(config["BACKEND"])(**config["CONFIG"])
    for host in layer.hosts:
        connection = create_pool(host).make_connection()  # not connected: nothing is sent
        timeout = connection.socket_timeout
        assert timeout is not None and math.isfinite(timeout), (
            f"the channel layer's Redis connections have no read timeout: a Redis lost during a "
            f"blocking pop would hang every consumer of the process (host {host})"
        )
        assert timeout >= layer.brpop_timeout + MARGIN_S, (
            f"the channel layer's Redis read timeout ({timeout} s) does not outlast its blocking "
            f"pop ({layer.brpop_timeout} s): consumers on a quiet page would die with 1011 (host {host})"
        )

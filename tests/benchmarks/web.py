"""The benchmark's clients of the site: a keep-alive HTTP client (bearer token or a session
from the login form) and WebSocket connections carrying that session."""
from __future__ import annotations

import asyncio
import http.client
import json
import re
import time
from dataclasses import dataclass
from typing import Any, AsyncIterator
from urllib.parse import urlencode

from websockets.asyncio.client import ClientConnection, connect

RECEIVE_POLL_S = 0.25
CSRF_FIELD = re.compile(r'name="csrfmiddlewaretoken" value="([^"]+)"')


@dataclass
class Response:
    status: int
    body: bytes
    ms: float  # from sending the request to the last byte of the answer

    def json(self) -> Any:
        return json.loads(self.body)


class Http:
    """One persistent HTTP/1.1 connection, as a script or a browser tab keeps it."""

    def __init__(self, host: str, port: int, token: str | None = None, timeout: float = 60.0) -> None:
        self.host, self.port, self.timeout = host, port, timeout
        self.token = token
        self.cookies: dict[str, str] = {}
        self._conn: http.client.HTTPConnection | None = None

    @property
    def origin(self) -> str:
        return f"http://{self.host}:{self.port}"

    def request(self, method: str, path: str, body: bytes | None = None,
                headers: dict[str, str] | None = None) -> Response:
        headers = dict(headers or {})
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        if self.cookies:
            headers["Cookie"] = self.cookie_header()
        for attempt in (1, 2):  # the server may have closed an idle keep-alive connection
            if self._conn is None:
                self._conn = http.client.HTTPConnection(self.host, self.port, timeout=self.timeout)
            began = time.perf_counter()
            try:
                self._conn.request(method, path, body=body, headers=headers)
                answer = self._conn.getresponse()
                data = answer.read()
            except (http.client.RemoteDisconnected, ConnectionError, http.client.CannotSendRequest):
                self.close()
                if attempt == 2:
                    raise
                continue
            ms = (time.perf_counter() - began) * 1000
            for cookie in answer.headers.get_all("Set-Cookie") or []:
                name, _, value = cookie.split(";", 1)[0].partition("=")
                self.cookies[name.strip()] = value.strip()
            if answer.getheader("Connection", "").lower() == "close":
                self.close()
            return Response(answer.status, data, ms)
        raise AssertionError("unreachable")

    def get(self, path: str) -> Response:
        return self.request("GET", path)

    def post_json(self, path: str, body: dict) -> Response:
        return self.request("POST", path, json.dumps(body).encode(), {"Content-Type": "application/json"})

    def transition(self, key: str, label: str) -> Response:
        return self.post_json(f"/api/v1/nodes/{key}/transition", {"transition": label})

    def login(self, username: str, password: str) -> None:
        """Log in through the login form, as a person does; keeps the session cookie."""
        page = self.get("/login/")
        match = CSRF_FIELD.search(page.body.decode())
        if page.status != 200 or match is None:
            raise RuntimeError(f"the login page answered {page.status} without a CSRF field")
        form = urlencode({"username": username, "password": password, "csrfmiddlewaretoken": match.group(1)})
        answer = self.request("POST", "/login/", form.encode(), {"Content-Type": "application/x-www-form-urlencoded"})
        if answer.status != 302 or "sessionid" not in self.cookies:
            raise RuntimeError(f"logging in as {username} failed (status {answer.status})")

    def cookie_header(self) -> str:
        return "; ".join(f"{k}={v}" for k, v in self.cookies.items())

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None


def ws_connect(web: Http, path: str) -> connect:
    """A WebSocket to the site with the session of ``web`` and the site's own Origin."""
    return connect(
        f"ws://{web.host}:{web.port}{path}",
        origin=web.origin,  # type: ignore[arg-type]
        additional_headers={"Cookie": web.cookie_header()},
        compression=None,
        proxy=None,
        max_size=8 * 1024 * 1024,
        open_timeout=10,
    )


__all__ = ["ClientConnection", "Http", "Response", "ws_connect"]


async def received(ws: ClientConnection, stop: asyncio.Event) -> AsyncIterator[tuple[float, str | bytes]]:
    """Each message of ``ws`` with its arrival (monotonic clock) until ``stop`` is set, which is
    looked at every RECEIVE_POLL_S while the socket is quiet."""
    while not stop.is_set():
        try:
            message = await asyncio.wait_for(ws.recv(), RECEIVE_POLL_S)
        except asyncio.TimeoutError:
            continue
        yield time.monotonic(), message

"""A small HTTPS client for talking to the app through the test's reverse proxy as a browser
would: cookies, the login form with its CSRF token, Origin/Referer, no automatic redirects."""
from __future__ import annotations

import http.client
import json
import re
import ssl
from http.cookies import SimpleCookie
from urllib.parse import urlencode


def insecure_context() -> ssl.SSLContext:
    """The test proxy's certificate is self-signed (as a device's often is)."""
    context = ssl.create_default_context()
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    return context


class Response:
    def __init__(self, status: int, headers: http.client.HTTPMessage, body: bytes) -> None:
        self.status, self.headers, self.body = status, headers, body

    @property
    def text(self) -> str:
        return self.body.decode("utf-8", errors="replace")

    def json(self):
        return json.loads(self.body)

    def __repr__(self) -> str:
        return f"<{self.status} {self.text[:300]!r}>"


class Browser:
    def __init__(self, host: str, port: int, timeout: float = 30) -> None:
        self.host, self.port, self.timeout = host, port, timeout
        self.cookies: dict[str, str] = {}

    @property
    def origin(self) -> str:
        return f"https://{self.host}:{self.port}"

    def cookie_header(self) -> str:
        return "; ".join(f"{k}={v}" for k, v in self.cookies.items())

    def request(self, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
                cookies: bool = True) -> Response:
        connection = http.client.HTTPSConnection(self.host, self.port, timeout=self.timeout, context=insecure_context())
        try:
            sent = {"Host": f"{self.host}:{self.port}", **(headers or {})}
            if cookies and self.cookies:
                sent["Cookie"] = self.cookie_header()
            connection.request(method, path, body=body, headers=sent)
            raw = connection.getresponse()
            response = Response(raw.status, raw.headers, raw.read())
        finally:
            connection.close()
        if cookies:
            for header in response.headers.get_all("Set-Cookie") or []:
                jar = SimpleCookie()
                jar.load(header)
                for name, morsel in jar.items():
                    self.cookies[name] = morsel.value
        return response

    def get(self, path: str, **kwargs) -> Response:
        return self.request("GET", path, **kwargs)

    def login(self, prefix: str, username: str, password: str) -> Response:
        page = self.get(f"{prefix}/login/")
        assert page.status == 200, f"login page: {page}"
        match = re.search(r'name="csrfmiddlewaretoken" value="([^"]+)"', page.text)
        assert match, "the login form has no CSRF token"
        action = re.search(r'<form[^>]*method="post"[^>]*action="([^"]*/login/)"', page.text)  # not the language form
        target = action.group(1) if action and action.group(1) else f"{prefix}/login/"
        form = urlencode({"username": username, "password": password,
                          "csrfmiddlewaretoken": match.group(1), "next": f"{prefix}/"})
        return self.request(
            "POST", target, body=form.encode(),
            headers={"Content-Type": "application/x-www-form-urlencoded", "Origin": self.origin,
                     "Referer": f"{self.origin}{prefix}/login/"},
        )

    def api(self, method: str, path: str, token: str, payload: dict | None = None) -> Response:
        headers = {"Authorization": f"Bearer {token}", "Accept": "application/json"}
        body = None
        if payload is not None:
            body = json.dumps(payload).encode()
            headers["Content-Type"] = "application/json"
        return self.request(method, path, body=body, headers=headers, cookies=False)

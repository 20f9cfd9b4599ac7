"""What the fuzzer of test_fuzz.py sends (drawn from a seeded random.Random), and what it checks
in each answer. Every endpoint of docs/api.md, every page of the dashboard and its forms."""
from __future__ import annotations

import json
import random
from dataclasses import dataclass, field
from urllib.parse import quote, urlencode

ROBOT = "fz-agv"
NODES = ("joy_to_vel", "lidar_driver", "camera_driver")
PARAMETERS = ("scale_linear", "deadman_button", "num_points", "frame_id", "range_min", "range_max",
              "scan_rate_hz", "drop_probability", "width", "height", "exposure_ms", "fps", "use_sim_time")
LOGIN_TRIES = 3  # wrong passwords from 127.0.0.1: below the lock-out (5), which other tests would feel
BAD_TOKENS = 3  # below too_many_bad_tokens (20) likewise

# JSON values of every kind. No transition id 5-7 nor "shutdown": a finalized node would take
# nothing more for the rest of the run (shutdown has tests of its own).
VALUES = [None, True, False, 0, 1, -1, 3, 8, 2**31, 2**63, -(2**63) - 1, 10**30, 0.5, -0.0, 1e308, -1e308,
          5e-324, "", " ", "configure", "activate", "deactivate", "cleanup", "CONFIGURE", " activate ", "3",
          "²", "١", "𝟑", "1" * 30, "x" * 3000, "\x00", "null", "'; DROP TABLE x; --", "<script>x</script>",
          "../../etc/passwd", "active", "inactive", "unconfigured", "bringup", "pause", "resume", "reset",
          "stop", "continue", "/joy_to_vel", [], {}, [1, 2], ["/joy_to_vel"], {"a": 1}, [[[]]], [1.5, "x"]]
# JSON text that json.dumps does not write: non-finite numbers, lone surrogates, overlong numbers.
RAW = ["NaN", "Infinity", "-Infinity", "1e999", "-1e999", '"\\ud800"', '"\\udfff\\ud800x"', '"\\u0000"',
       "9" * 5000, "1" + "0" * 400, "1." + "0" * 5000, "[" * 50 + "]" * 50, "0x10", "01", "tru", "'x'"]
TIMEOUTS = [None, 1, 2.5, 10, 25, 0, -1, 26, 1e308, "5", True, [], {}]
WAITS = ["", "0", "1", "2", "nan", "inf", "1e999", "-3", "abc", "²", "0.5"]
IDS = ["", "x", f"{ROBOT}.", f"{ROBOT}.nope", "..", ".", "\x00", "²", "a/b", "ñ", "x" * 2000, " ",
       f"{ROBOT}.joy_to_vel ", f"{ROBOT.upper()}.JOY_TO_VEL", "%", "'", '"', "<b>"]
RAW_PIECES = ["%ZZ", "%FF", "%C0%AF", "%2e%2e", "%u0041", "%"]  # put in a path as they are
CHAOS = [b"", b"{", b"}", b"[]", b'"x"', b"null", b"\xff\xfe\x00", b"\x00" * 10, b"{" * 3000, b"[" * 100_000,
         b'{"a":' * 500, "{\"transition\": \"configure\"}".encode("utf-16"), b"x" * 200_000]


@dataclass
class Credentials:
    operator_token: str
    viewer_token: str
    operator_session: str
    admin_session: str
    csrf: str


@dataclass
class Case:
    method: str
    target: str  # path and query, as sent
    body: bytes = b""
    headers: dict[str, str] = field(default_factory=dict)
    kind: str = "api"  # api, yaml (the parameter file export), page
    endpoint: str = ""

    def raw(self) -> bytes:
        lines = [f"{self.method} {self.target} HTTP/1.1", "Host: 127.0.0.1", "Connection: close"]
        lines += [f"{k}: {v}" for k, v in self.headers.items()]
        if self.body or self.method in ("POST", "PUT", "PATCH"):
            lines.append(f"Content-Length: {len(self.body)}")
        return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + self.body

    def __str__(self) -> str:
        return f"{self.method} {self.target[:150]} body={self.body[:150]!r} headers={list(self.headers)}"


@dataclass
class Reached:
    transition_record: int | None = None  # the record id of a transition that reached the robot
    parameter_results: int = 0  # parameters the node was asked to set


class Fuzzer:
    def __init__(self, rng: random.Random, who: Credentials) -> None:
        self.rng, self.who = rng, who
        self.bad_tokens = self.logins = 0

    # --- pieces ---------------------------------------------------------------------------------
    def value(self) -> str:
        """A JSON value, as text."""
        if self.rng.random() < 0.15:
            return self.rng.choice(RAW)
        return json.dumps(self.rng.choice(VALUES))

    def text(self) -> str:
        value = self.rng.choice(VALUES + WAITS)
        return value if isinstance(value, str) else json.dumps(value)

    def node_id(self) -> str:
        if self.rng.random() < 0.75:
            return quote(f"{ROBOT}.{self.rng.choice(NODES)}", safe="")
        if self.rng.random() < 0.2:
            return self.rng.choice(RAW_PIECES)
        return quote(self.rng.choice(IDS), safe="")

    def robot(self) -> str:
        return ROBOT if self.rng.random() < 0.8 else quote(self.rng.choice(IDS), safe="")

    def query(self, *names: str) -> str:
        chosen = [(n, self.text()) for n in names if self.rng.random() < 0.5]
        if self.rng.random() < 0.05:
            chosen += [(f"f{i}", "1") for i in range(1200)]  # over DATA_UPLOAD_MAX_NUMBER_FIELDS
        return "?" + urlencode(chosen) if chosen else ""

    def obj(self, fields: dict[str, str]) -> bytes:
        """A JSON object of these fields (name: value text), some left out, some added."""
        parts = [f"{json.dumps(k)}: {v}" for k, v in fields.items() if self.rng.random() < 0.9]
        if self.rng.random() < 0.2:
            parts.append(f'"extra": {self.value()}')
        return ("{" + ", ".join(parts) + "}").encode()

    def body(self, good: bytes) -> bytes:
        return good if self.rng.random() < 0.8 else self.rng.choice(CHAOS)

    def api_headers(self, write: bool) -> dict[str, str]:
        headers = {"Content-Type": "application/json"} if write else {}
        roll = self.rng.random()
        if roll < 0.8:
            headers["Authorization"] = f"Bearer {self.who.operator_token}"
        elif roll < 0.87:
            headers["Authorization"] = f"Bearer {self.who.viewer_token}"
        elif roll < 0.93:
            headers.update(self.session(csrf=self.rng.random() < 0.7))
        elif roll < 0.95 and self.bad_tokens < BAD_TOKENS:
            self.bad_tokens += 1
            headers["Authorization"] = self.rng.choice(["Bearer lcm_nope", "Basic eDp5", "Bearer ", "Bearer \t"])
        return headers

    def session(self, csrf: bool = True, admin: bool = False) -> dict[str, str]:
        sid = self.who.admin_session if admin else self.who.operator_session
        headers = {"Cookie": f"sessionid={sid}; csrftoken={self.who.csrf}"}
        if csrf:
            headers["X-CSRFToken"] = self.who.csrf
        if self.rng.random() < 0.3:
            headers["HX-Request"] = "true"
        return headers

    # --- requests -------------------------------------------------------------------------------
    def api(self) -> Case:
        rng, node = self.rng, self.node_id()
        timeout = json.dumps(rng.choice(TIMEOUTS)) if rng.random() < 0.9 else self.value()
        choices = [
            (8, "POST", f"/nodes/{node}/transition", lambda: self.obj(
                {"transition": json.dumps(rng.choice(["configure", "activate", "deactivate", "cleanup", 1, 2, 3, 4]))
                 if rng.random() < 0.7 else self.value(), "timeout": timeout}), "transition"),
            (3, "PATCH", f"/nodes/{node}/parameters", self.parameters, "parameters"),
            (2, "PUT", f"/nodes/{node}/desired-state", lambda: self.obj({"desired_state": self.value()}), ""),
            (1, "POST", f"/robots/{self.robot()}/operations{self.query('wait')}", lambda: self.obj({
                "operation": json.dumps(rng.choice(["bringup", "pause", "resume", "reset"]))
                if rng.random() < 0.6 else self.value(), "policy": self.value(), "timeout": timeout,
                "nodes": json.dumps(rng.sample([f"/{n}" for n in NODES], rng.randint(0, 3)))
                if rng.random() < 0.7 else self.value()}), ""),
            (1, "POST", f"/nodes/{node}/restart{self.query('wait')}", lambda: self.obj({"timeout": timeout}), ""),
            (1, "GET", "/gateways", None, ""), (1, "GET", "/robots", None, ""),
            (1, "GET", f"/nodes{self.query('robot')}", None, ""),
            (2, "GET", f"/nodes/{node}", None, ""),
            (1, "GET", f"/nodes/{node}/logs{self.query('level', 'limit')}", None, ""),
            (1, "GET", f"/transitions{self.query('robot', 'node', 'limit')}", None, ""),
            (1, "GET", f"/robots/{self.robot()}/runs", None, ""),
            (1, "GET", f"/runs/{quote(self.text(), safe='')}{self.query('wait')}", None, ""),
            (1, "GET", f"/nodes/{node}/parameters", None, ""),
            (1, "GET", f"/nodes/{node}/parameters.yaml", None, "yaml"),
            (1, rng.choice(["GET", "POST", "PUT", "DELETE"]), f"/{quote(self.text(), safe='/')}", None, ""),
        ]
        _, method, path, make, endpoint = rng.choices(choices, weights=[c[0] for c in choices])[0]
        if rng.random() < 0.04:  # the wrong method
            method = rng.choice(["GET", "POST", "PUT", "PATCH", "DELETE", "OPTIONS", "HEAD", "TRACE"])
        body = self.body(make()) if make and method not in ("GET", "HEAD") else b""
        kind = "yaml" if endpoint == "yaml" else "api"
        return Case(method, "/api/v1" + path, body, self.api_headers(bool(body)), kind, endpoint)

    def parameters(self) -> bytes:
        rng = self.rng
        if rng.random() < 0.03:
            return json.dumps({f"p{i}": 1 for i in range(201)}).encode()  # over MAX_PARAMETERS
        names = [rng.choice(PARAMETERS) if rng.random() < 0.7 else self.text() for _ in range(rng.randint(1, 4))]
        good = [1, 2, 0.5, 1.0, 30.0, 10, "laser", True, 640]
        return self.obj({name: json.dumps(rng.choice(good)) if rng.random() < 0.5 else self.value() for name in names})

    def page(self) -> Case:
        rng, node = self.rng, self.node_id()
        scope = rng.choice(["node", "robot", "robot", "x", quote(self.text(), safe="")])
        name = node if scope == "node" else self.robot()
        audit = self.query("kind", "robot", "node", "user", "outcome", "source", "since", "until", "page")
        path = rng.choice([
            f"/{self.query('robot', 'state', 'q')}", f"/nodes/{node}/", f"/audit/{audit}", f"/audit.csv{audit}",
            f"/logs/{scope}/{name}/{self.query('level', 'q')}", f"/logs/{scope}/{name}/download{self.query('level')}",
            f"/logs/{scope}/{name}/since{self.query('after', 'level')}", f"/nodes/{node}/parameters", "/login/",
            "/admin/", "/admin/login/", f"/admin/fleet/robot/{self.query('q')}", "/admin/fleet/managednode/",
            f"/admin/audit/transitionrecord/{self.query('q', 'o')}", "/static/nope.css", "/favicon.ico",
        ])
        roll = rng.random()
        headers = self.session(admin=roll < 0.2) if roll < 0.9 else {}
        return Case("GET", path, headers=headers, kind="page")

    def form(self) -> Case:
        rng, node = self.rng, self.node_id()
        fields: list[tuple[str, str]]
        path = rng.choice(["transition", "operations", "restart", "desired-state", "parameters", "import", "apply",
                           "watch", "login"])
        if path == "login":
            if self.logins >= LOGIN_TRIES:
                path = "transition"
            else:
                self.logins += 1
                target = rng.choice(["/login/", "/admin/login/"])
                fields = [("username", f"fuzz-nobody-{self.logins}"), ("password", self.text())]
                return Case("POST", target, urlencode(fields).encode(), {
                    **self.session(), "Content-Type": "application/x-www-form-urlencoded"}, "page")
        if path == "import":  # (deeply nested YAML and YAML aliases: test_fuzz.py, xfail for now)
            boundary = "fuzzboundary"
            content = rng.choice([b"", b"x: [", b"/**:\n  ros__parameters:\n    fps: 30\n", b"\xff" * 10,
                                  b"a: " + b"[" * 50, b"joy_to_vel:\n  ros__parameters:\n    scale_linear: .nan\n"])
            body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"p.yaml\"\r\n"
                    "Content-Type: application/x-yaml\r\n\r\n").encode() + content + f"\r\n--{boundary}--\r\n".encode()
            headers = {**self.session(), "Content-Type": f"multipart/form-data; boundary={boundary}"}
            return Case("POST", f"/nodes/{node}/parameters/import", body, headers, "page")
        fields = {
            "transition": [("transition", self.text())],
            "operations": [("operation", self.text()), ("policy", self.text()), ("timeout", self.text())],
            "restart": [],
            "desired-state": [("desired_state", self.text())],
            "parameters": [(f"seen:{p}", "1") for p in rng.sample(PARAMETERS, 2)]
            + [(f"value:{rng.choice(PARAMETERS)}", self.text())],
            "apply": [("values", rng.choice(RAW + [json.dumps({"fps": 30}), self.value()]))],
            "watch": [("name", self.text())],
        }[path]
        target = f"/robots/{self.robot()}/{path}" if path in ("operations", "watch") else f"/nodes/{node}/{path}"
        if path == "apply":
            target = f"/nodes/{node}/parameters/apply"
        roll = rng.random()
        headers = self.session(csrf=roll < 0.9) if roll < 0.95 else {}
        headers["Content-Type"] = "application/x-www-form-urlencoded"
        return Case("POST", target, urlencode(fields).encode(), headers, "page")

    def draw(self) -> Case:
        roll = self.rng.random()
        return self.api() if roll < 0.7 else self.page() if roll < 0.85 else self.form()


def check(case: Case, status: int, headers: dict[str, str], body: bytes) -> str:
    """What is wrong with this answer ("" if nothing)."""
    if status == 0:
        return f"no answer: {body[:200]!r}"
    if status >= 500:
        return f"{status}: {body[:300]!r}"
    kind = headers.get("content-type", "")
    if case.kind == "page" or case.method == "HEAD":
        return ""
    if case.kind == "yaml" and status == 200:
        return "" if kind.startswith("application/x-yaml") else f"YAML export as {kind}"
    if not kind.startswith("application/json"):
        return f"{status} as {kind!r}: {body[:200]!r}"
    try:
        answer = json.loads(body)
    except ValueError as exc:
        return f"{status}, not JSON ({exc}): {body[:200]!r}"
    if status >= 400:
        error = answer.get("error") if isinstance(answer, dict) else None
        if not (isinstance(error, dict) and isinstance(error.get("code"), str) and error.get("message")):
            return f"{status} not in the error shape: {body[:200]!r}"
    return ""


def reached(case: Case, status: int, body: bytes) -> Reached:
    """What of this (well answered) request reached the robot and must be in the audit log."""
    if case.method == "POST" and case.endpoint == "transition" and status in (200, 409, 422, 503, 504):
        answer = json.loads(body)
        record = answer.get("record_id", answer.get("error", {}).get("record_id"))
        return Reached(transition_record=record if record is not None else -1)
    if case.method == "PATCH" and case.endpoint == "parameters" and status in (200, 422):
        answer = json.loads(body)
        return Reached(parameter_results=len(answer.get("results", answer.get("error", {}).get("results", []))))
    return Reached()

"""Compose projects of the deploy tests (the Industrial Edge stack behind an nginx that behaves
like the device's; the plain site and a remote cell) and their clean-up."""
from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from tests.deploy.engine import ARTIFACTS, EDGE_DIR, ROOT, DeployError, run, wait_for


def stats_bytes(text: str) -> float:
    """A size as `docker stats` prints it: 84.17MiB, 1.2GiB, 512KiB, 900B (also kB/MB/GB)."""
    units = {"b": 1, "kib": 1024, "mib": 1024**2, "gib": 1024**3, "kb": 1000, "mb": 1000**2, "gb": 1000**3}
    match = re.fullmatch(r"\s*([\d.]+)\s*([A-Za-z]+)\s*", text)
    if not match or match.group(2).lower() not in units:
        raise ValueError(f"not a docker stats size: {text!r}")
    return float(match.group(1)) * units[match.group(2).lower()]


def mem_limit_bytes(text) -> int:
    """A compose mem_limit (160mb, 1g, 268435456): Docker reads k/m/g, with or without b, as binary."""
    match = re.fullmatch(r"\s*(\d+)\s*([bkmg]?)b?\s*", str(text).lower())
    if not match:
        raise ValueError(f"not a mem_limit: {text!r}")
    return int(match.group(1)) * {"": 1, "b": 1, "k": 1024, "m": 1024**2, "g": 1024**3}[match.group(2)]


@dataclass
class Stack:
    project: str
    workdir: Path
    files: list[str]
    web_port: int
    proxy_port: int = 0
    admin_password: str = ""
    nginx: subprocess.Popen | None = None
    created_network: bool = False
    extra: dict = field(default_factory=dict)
    logs: str = "compose"  # tests/artifacts/deploy/<logs>.log and <logs>-down.log

    def compose(self, *args: str, timeout: float = 180, check: bool = True) -> subprocess.CompletedProcess:
        argv = ["docker-compose", "-p", self.project]
        for name in self.files:
            argv += ["-f", name]
        return run(argv + list(args), timeout=timeout, check=check, cwd=self.workdir)

    def container(self, service: str) -> str:
        cid = self.compose("ps", "-q", service, timeout=60).stdout.strip()
        if not cid:
            raise AssertionError(f"no container for service {service}")
        return cid

    def health(self, service: str) -> str:
        return run(
            ["docker", "inspect", "-f", "{{if .State.Health}}{{.State.Health.Status}}{{else}}none{{end}}",
             self.container(service)], timeout=30,
        ).stdout.strip()

    def manage(self, *args: str) -> str:
        return run(["docker", "exec", self.container("web"), "python", "manage.py", *args], timeout=120).stdout.strip()

    @property
    def base_url(self) -> str:
        return f"https://127.0.0.1:{self.proxy_port}"

    def save_logs(self) -> None:
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        result = self.compose("logs", "--no-color", "--tail", "400", timeout=120, check=False)
        (ARTIFACTS / f"{self.logs}.log").write_text(result.stdout + result.stderr)

    def down(self) -> None:
        """compose down (containers, networks, volume); whatever it leaves is removed by label."""
        try:
            result = self.compose("down", "-v", "--remove-orphans", "--timeout", "10", timeout=180, check=False)
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            (ARTIFACTS / f"{self.logs}-down.log").write_text(
                f"exit {result.returncode}\n{result.stdout}{result.stderr}")
            self.down_by_label()
        finally:
            if self.created_network:
                run(["docker", "network", "rm", "proxy-redirect"], timeout=60, check=False)

    def down_by_label(self) -> None:
        label = f"label=com.docker.compose.project={self.project}"
        left = run(["docker", "ps", "-aq", "--filter", label], timeout=60, check=False).stdout.split()
        if left:
            run(["docker", "rm", "-f", "-v", *left], timeout=120, check=False)
        for kind in ("network", "volume"):
            names = run(["docker", kind, "ls", "-q", "--filter", label], timeout=60, check=False).stdout.split()
            if names:
                run(["docker", kind, "rm", *names], timeout=120, check=False)

    def leftovers(self) -> list[str]:
        label = f"label=com.docker.compose.project={self.project}"
        found = []
        for kind in ("container", "network", "volume"):
            argv = ["docker", kind, "ls", "-q", "--filter", label] + (["-a"] if kind == "container" else [])
            found += [f"{kind} {name}" for name in run(argv, timeout=60, check=False).stdout.split()]
        return found


def remove_stale_projects() -> list[str]:
    """Compose projects of earlier deploy-test runs whose pytest process is gone (a run that was
    killed before its teardown): their containers, networks and volumes are removed. Projects
    are named lcdeploy<pid>[suffix]; networks the tests create carry the project label too."""
    labels = []
    for kind in ("ps -a", "network ls", "volume ls"):
        labels += run(
            ["docker", *kind.split(), "--format", '{{.Label "com.docker.compose.project"}}'], timeout=60, check=False
        ).stdout.split()
    stale = []
    for project in sorted(set(labels)):
        match = re.fullmatch(r"lcdeploy(\d+)[a-z]*", project)
        if match and not Path(f"/proc/{match.group(1)}").exists():
            Stack(project=project, workdir=ROOT, files=[], web_port=0).down_by_label()
            stale.append(project)
    return stale


def nginx_location_headers(nginx_json: dict, service: str = "web") -> tuple[str, list[str], str]:
    """(name, header directives, rewrite target) of the reverse-proxy entry, as the device uses them."""
    entry = nginx_json[service][0]
    headers = json.loads(entry["headers"]) if entry.get("headers") else {}
    directives = [f'{key} "{value}";' for key, value in headers.items()]
    return entry["name"], directives, entry.get("rewriteTarget", "/")


def start_nginx(workdir: Path, proxy_port: int, web_port: int) -> subprocess.Popen:
    """Debian's nginx on loopback with TLS, set up like the device's: /<name>/ is stripped and
    proxied to the app's web service, with the headers from docker/edge/nginx.json."""
    name, header_lines, rewrite_target = nginx_location_headers(json.loads((EDGE_DIR / "nginx.json").read_text()))
    workdir.mkdir(parents=True, exist_ok=True)
    for sub in ("body", "proxy", "fastcgi", "uwsgi", "scgi"):
        (workdir / sub).mkdir(exist_ok=True)
        (workdir / sub).chmod(0o777)
    run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
         "-keyout", str(workdir / "key.pem"), "-out", str(workdir / "cert.pem"), "-days", "2",
         "-subj", "/CN=127.0.0.1"],
        timeout=60,
    )
    headers = "\n            ".join(header_lines)
    config = f"""
worker_processes 1;
pid {workdir}/nginx.pid;
error_log {workdir}/error.log info;
events {{ worker_connections 256; }}
http {{
    access_log {workdir}/access.log;
    client_body_temp_path {workdir}/body;
    proxy_temp_path {workdir}/proxy;
    fastcgi_temp_path {workdir}/fastcgi;
    uwsgi_temp_path {workdir}/uwsgi;
    scgi_temp_path {workdir}/scgi;
    server {{
        listen 127.0.0.1:{proxy_port} ssl;
        ssl_certificate {workdir}/cert.pem;
        ssl_certificate_key {workdir}/key.pem;
        location = /{name} {{ return 301 https://$http_host/{name}/; }}
        location ~* ^/{name}/ {{
            rewrite /{name}/(.*) {rewrite_target}$1 break;
            proxy_pass http://127.0.0.1:{web_port};
            proxy_http_version 1.1;
            proxy_set_header Host $http_host;
            proxy_set_header X-Real-IP $remote_addr;
            proxy_set_header X-Forwarded-For $proxy_add_x_forwarded_for;
            {headers}
            proxy_read_timeout 300s;
        }}
    }}
}}
"""
    conf = workdir / "nginx.conf"
    conf.write_text(config)
    run(["nginx", "-t", "-p", str(workdir), "-c", str(conf)], timeout=30)
    with open(workdir / "nginx.out", "ab") as out:
        process = subprocess.Popen(
            ["nginx", "-p", str(workdir), "-c", str(conf), "-g", "daemon off;"],
            stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
        )

    def listening() -> bool:
        if process.poll() is not None:
            raise DeployError(f"nginx exited:\n{(workdir / 'error.log').read_text(errors='replace')}")
        with socket.socket() as probe:
            return probe.connect_ex(("127.0.0.1", proxy_port)) == 0

    wait_for(listening, 15, "nginx to listen")
    return process


def stop_process(process: subprocess.Popen | None, timeout: float = 10) -> None:
    if process is None or process.poll() is not None:
        return
    os.killpg(process.pid, signal.SIGTERM)
    try:
        process.wait(timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait(5)


def yaml_services(*paths: Path) -> dict:
    """The services of compose files merged as docker-compose merges an override into the file
    before it: a service's keys replaced, its lists of networks joined."""
    import yaml

    services: dict = {}
    for path in paths:
        for name, service in yaml.safe_load(path.read_text())["services"].items():
            merged = services.setdefault(name, {})
            for key, value in service.items():
                if key == "networks" and isinstance(merged.get(key), list) and isinstance(value, list):
                    merged[key] = merged[key] + [n for n in value if n not in merged[key]]
                else:
                    merged[key] = value
    return services

"""``manage.py run_demo`` (what ``make demo`` runs): the whole product on one machine.

Starts Redis (unless its own, or the one REDIS_URL names, answers already), migrates, makes sure an admin exists (its
generated password is kept in the data dir and printed), registers two demo robots on the
gateway "local" with their node processes as its launch profiles (the gateway runs those), then
supervises that gateway, the ingest process that stores what it reports and daphne until Ctrl-C.
"""
from __future__ import annotations

import os
import secrets
import signal
import socket
import sys
import time
from pathlib import Path
from urllib.parse import urlparse

from django.conf import settings
from django.contrib.auth import get_user_model
from django.core.management import call_command
from django.core.management.base import BaseCommand, CommandError

from lifecycle_site import local_redis
from lifecycle_site.fleet.models import Gateway, ProcessProfile, Robot
from lifecycle_site.supervisor import Child, Supervisor

DEMO_ROBOTS = [
    # name, domain id, autostart of the main node process
    ("agv-1", int(os.environ.get("DEMO_DOMAIN_AGV1", 21)), "none"),
    ("agv-2", int(os.environ.get("DEMO_DOMAIN_AGV2", 22)), "activate"),
]
MAIN_NODES = "joy_to_vel,joystick,lidar_driver,camera_driver,planner"


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def free_port(preferred: int) -> int:
    for port in range(preferred, preferred + 50):
        with socket.socket() as probe:
            if probe.connect_ex(("127.0.0.1", port)) != 0:
                return port
    raise CommandError(f"No free port in {preferred}-{preferred + 49}.")


def _running_demo(data: Path) -> int | None:
    """The pid of the demo running from ``data`` (its demo.pid, of a live process), or None."""
    try:
        pid = int((data / "demo.pid").read_text().split()[0])
        os.kill(pid, 0)
    except (OSError, ValueError, IndexError):
        return None
    return pid


class Command(BaseCommand):
    help = "Run the lifecycle manager with two demo robots on this machine (Ctrl-C stops everything)."

    def add_arguments(self, parser) -> None:
        parser.add_argument("--port", type=int, default=int(os.environ.get("PORT", 8000)))
        parser.add_argument("--no-robots", action="store_true", help="Do not start the demo robots")
        parser.add_argument("--check", action="store_true", help="Start, verify, print, then stop (for CI)")

    def handle(self, *args, port: int, no_robots: bool, check: bool, **options) -> None:
        os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
        data = Path(settings.DATA_DIR)
        self._claim_data_dir(data)
        # Ctrl-C, `kill`, a closed terminal or a CI timeout all stop the demo cleanly (SIGINT
        # included: a shell that starts us in the background would have it ignored).
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(sig, _interrupt)
        supervisor = Supervisor()
        redis_process = None
        try:
            redis_process = self._ensure_redis(data, chosen="REDIS_URL" in os.environ)
            call_command("migrate", verbosity=0)
            user, password = self._ensure_admin(data)
            local, _ = Gateway.objects.get_or_create(name="local")
            for name, domain, _ in DEMO_ROBOTS:
                robot, _ = Robot.objects.get_or_create(
                    name=name, defaults={"domain_id": domain, "auto_recover": True, "gateway": local}
                )
                if robot.domain_id != domain or not robot.enabled or robot.gateway_id != local.id:
                    robot.domain_id, robot.enabled, robot.gateway = domain, True, local
                    robot.save()
            self._demo_profiles(no_robots)
            call_command("demo_modes", *(name for name, _, _ in DEMO_ROBOTS))  # (the modes app's: docs/modes.md)
            port = free_port(port)
            self._start_children(supervisor, data, port, no_robots)
            url = f"http://127.0.0.1:{port}/"
            self._wait_for_site(url, supervisor)
            self.stdout.write(self.style.SUCCESS(f"\nLifecycle manager running at {url}"))
            self.stdout.write(f"Log in as {user} with password {password}")
            self.stdout.write(
                f"Demo robots: {', '.join(f'{n} (ROS domain {d})' for n, d, _ in DEMO_ROBOTS)}. "
                f"Their processes: the robots' Processes pages. Logs of the others: {data / 'logs'}. "
                "Ctrl-C stops everything.\n"
            )
            self.stdout.flush()  # also when the output goes to a file or a pipe (block-buffered)
            if check:
                return
            while True:
                supervisor.watch_once(lambda text: (self.stdout.write(f"[demo] {text}"), self.stdout.flush()))
                time.sleep(0.5)
        except KeyboardInterrupt:
            self.stdout.write("\nStopping the demo ...")
        finally:
            supervisor.stop()
            if redis_process is not None:
                redis_process.terminate()
                redis_process.wait(5)
            (data / "demo.pid").unlink(missing_ok=True)

    def _claim_data_dir(self, data: Path) -> None:
        """One demo per data dir: a second one would run a second gateway on the same facts."""
        pid_file = data / "demo.pid"
        other = _running_demo(data)  # a stale file (that demo is gone) is written over
        if other is not None:
            raise CommandError(
                f"A demo is already running from {data} (pid {other}); stop it first "
                "(Ctrl-C in its terminal, or kill it), or set LIFECYCLE_DATA_DIR to run another."
            )
        pid_file.write_text(f"{os.getpid()}\n")
    def _ensure_redis(self, data: Path, chosen: bool):
        """This data dir's Redis: started here, or found answering. One that answers must not be
        another demo's (two sites on one Redis take each other's commands and facts), nor, at
        the default address, anyone else's; one named in REDIS_URL (``chosen``) is taken."""
        url = settings.REDIS_URL
        if local_redis.answers(url):
            self._refuse_if_not_ours(url, data, chosen)
            return None
        parsed = urlparse(url)
        if parsed.hostname not in ("127.0.0.1", "localhost"):
            raise CommandError(f"Redis at {url} does not answer; start it or set REDIS_URL.")
        self.stdout.write(f"Starting Redis on 127.0.0.1:{parsed.port or 6379} ...")
        return local_redis.start(parsed.port or 6379, data / "redis")

    def _refuse_if_not_ours(self, url: str, data: Path, chosen: bool) -> None:
        own = (data / "redis").resolve()
        found = local_redis.directory(url)
        if found == own:
            return  # this data dir's (started by an earlier demo of it)
        def way_out() -> str:
            return (f"give this demo a Redis of its own: REDIS_URL=redis://127.0.0.1:"
                    f"{free_port(urlparse(url).port or 6379)}/0 make demo (and, for robots of its own, "
                    "DEMO_DOMAIN_AGV1 and DEMO_DOMAIN_AGV2, e.g. 31 and 32).")

        other = _running_demo(found.parent) if found is not None else None
        if other is not None:
            raise CommandError(
                f"The Redis at {url} is the one of the demo running from {found.parent} (pid {other}): "
                f"this demo (data dir {data}) would share it, and two sites on one Redis take each other's "
                f"commands and facts. Stop that demo first, or {way_out()}")
        if not chosen:
            where = f"it keeps its files in {found}" if found else "it does not say where it keeps its files"
            raise CommandError(
                f"A Redis answers at {url}, but it is not this demo's ({where}, not in {own}). "
                f"To use it all the same, set REDIS_URL={url}; or {way_out()}")

    def _ensure_admin(self, data: Path) -> tuple[str, str]:
        """An admin for the demo; its generated password lives only in the data dir (0600)."""
        users = get_user_model().objects
        secret = data / "demo-admin-password"
        if not users.filter(username="admin").exists():
            password = secrets.token_urlsafe(12)
            users.create_superuser("admin", "", password)
            secret.touch(mode=0o600)
            secret.write_text(password)
        if secret.exists():
            return "admin", secret.read_text().strip()
        return "admin", "(the password you set; reset it with 'manage.py changepassword admin')"

    @staticmethod
    def _demo_profiles(no_robots: bool) -> None:
        """The demo robots' node processes are launch profiles of the gateway "local", which runs
        them as their supervisor (docs/processes.md): their pages offer restart, stop and start,
        a crash is respawned, and a hung or finalized node is brought back by restarting its process.
        The node that can be made to crash or hang runs alone, so that takes only it down."""
        for name, domain, autostart in DEMO_ROBOTS:
            robot = Robot.objects.get(name=name)
            common = ["-m", "ros_gateway.demo.robot", "--domain", str(domain)]
            # Both publish diagnostics; the battery monitor runs beside the main nodes, and agv-2 also
            # has an aggregator's /diagnostics_agg (a tree by subsystem, as diagnostic_aggregator makes).
            main = [*common, "--nodes", MAIN_NODES, "--autostart", autostart,
                    *(["--diagnostics-agg"] if name == "agv-2" else [])]
            for process, args in (("nodes", main), ("flaky_node", [*common, "--nodes", "flaky_node", "--no-battery"])):
                ProcessProfile.objects.update_or_create(robot=robot, name=process, defaults={
                    "command": sys.executable, "args": args, "cwd": str(settings.BASE_DIR), "enabled": not no_robots,
                    "env": {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, "stop_grace_s": 3.0})

    def _start_children(self, supervisor: Supervisor, data: Path, port: int, no_robots: bool) -> None:
        python = sys.executable
        logs = data / "logs"
        supervisor.add(Child("ingest", [python, "manage.py", "ingest"], logs / "ingest.log"))
        supervisor.add(Child("ros_gateway", [python, "-m", "ros_gateway"], logs / "gateway.log"))
        supervisor.add(
            Child(
                "daphne",
                # daphne, answering at its HTTP limits (lifecycle_site/serve.py)
                [python, "-m", "lifecycle_site.serve", "-b", "127.0.0.1", "-p", str(port),
                 "lifecycle_site.asgi:application"],
                logs / "daphne.log",
            )
        )

    def _wait_for_site(self, url: str, supervisor: Supervisor, wait: float = 30.0) -> None:
        import urllib.error
        import urllib.request

        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(url + "login/", timeout=2):
                    return
            except (urllib.error.URLError, ConnectionError, OSError):
                time.sleep(0.3)
        raise CommandError(f"The site did not come up at {url} within {wait:g} s; see {settings.DATA_DIR}/logs.")

"""Launch profiles for the supervised scenario (supervised.py): written in the stack's database
through ``manage.py shell`` (the first functions, run inside the site), read back through the API,
and the scenario's processes found in /proc (none may outlive its stack)."""
from __future__ import annotations

import time
from pathlib import Path

from tests.benchmarks.harness import Stack
from tests.benchmarks.processes import PYTHON, ROOT, BenchError, run_manage, wait_for

PREFIX = "sup"  # every node prefix of the scenario begins so (survivors are found by it)
SLEEP_ARG = "864209"  # ``sleep 864209`` (10 days): the cheap supervised process, known by its argument
START_TIMEOUT_S = 90.0


# -- inside the site (manage.py shell) ---------------------------------------------------------
def robot_args(domain: int, generic: int, prefix: str) -> list[str]:
    """A demo robot process as the harness starts one (Stack.start_robot), as a profile's arguments."""
    return ["-m", "ros_gateway.demo.robot", "--domain", str(domain), "--nodes", "", "--generic", str(generic),
            "--generic-prefix", prefix, "--ros-args", "--disable-external-lib-logs"]


def demo_robot(name: str, domain: int, generic: int, prefix: str) -> dict:
    """A profile running a demo robot process (the harness's Python, from the repository root)."""
    return {"name": name, "command": PYTHON, "args": robot_args(domain, generic, prefix)}


def sleeper(name: str) -> dict:
    """A profile running a process that only waits (found on the gateway's PATH)."""
    return {"name": name, "command": "sleep", "args": [SLEEP_ARG]}


def add_profiles(robot_name: str, profiles: list[dict]) -> None:
    """A launch profile per spec (name, command, args), respawn on, the stop signal and grace as
    installed; the robot recovers its nodes automatically. One transaction, so the gateway's config
    is published once (on commit)."""
    from django.db import transaction

    from lifecycle_site.fleet.models import ProcessProfile, Robot

    with transaction.atomic():
        robot = Robot.objects.get(name=robot_name)
        for spec in profiles:
            ProcessProfile.objects.create(robot=robot, cwd=str(ROOT), respawn=True,
                                          env={"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, **spec)
        robot.auto_recover = True
        robot.save()


def want_active(robot_name: str, prefix: str) -> int:
    """Desired state ``active`` for the robot's nodes named <prefix>_NNN; saving the robot publishes
    its gateway's config (a queryset update sends no signal). Returns how many nodes."""
    from django.db import transaction

    from lifecycle_site.fleet.models import ManagedNode, Robot

    with transaction.atomic():
        count = ManagedNode.objects.filter(robot__name=robot_name, name__startswith=f"/{prefix}_").update(
            desired_state="active")
        Robot.objects.get(name=robot_name).save()
    return count


def remove_profiles(robot_name: str) -> int:
    """Delete the robot's launch profiles: its gateway stops their processes."""
    from django.db import transaction

    from lifecycle_site.fleet.models import ProcessProfile

    with transaction.atomic():
        count, _ = ProcessProfile.objects.filter(robot__name=robot_name).delete()
    return count


def in_site(stack: Stack, call: str) -> str:
    """One of the functions above, run with the stack's settings (one Django start)."""
    return run_manage(stack.env, "shell", "-c",
                      f"from tests.benchmarks import launch_profiles\nprint(launch_profiles.{call})")


# -- what the API says -------------------------------------------------------------------------
def processes(stack: Stack, robot: str) -> dict[str, dict]:
    answer = stack.api.get(f"/api/v1/robots/{robot}/processes")
    if answer.status != 200:
        raise BenchError(f"GET processes of {robot} answered {answer.status}: {answer.body[:300]!r}")
    return {p["name"]: p for p in answer.json()["processes"]}


def wait_running(stack: Stack, robot: str, names: list[str], pids: set[int]) -> dict[str, int]:
    """Until the gateway reports every named profile running; their pids (remembered in ``pids``)."""
    def running() -> dict[str, int] | None:
        listed = processes(stack, robot)
        if all(listed.get(n, {}).get("status") == "running" and listed[n].get("pid") for n in names):
            return {n: listed[n]["pid"] for n in names}
        return None

    found = wait_for(running, START_TIMEOUT_S, f"{len(names)} processes of {robot} to run", 0.25)
    pids.update(found.values())
    return found


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def ours(pid: int) -> bool:
    """A process of this scenario's profiles (by its command line: a pid may have been reused)."""
    try:
        argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return False
    if argv[0].endswith("sleep") and argv[1:2] == [SLEEP_ARG]:
        return True
    if "ros_gateway.demo.robot" not in argv or "--generic-prefix" not in argv:
        return False
    position = argv.index("--generic-prefix") + 1
    return position < len(argv) and argv[position].startswith(PREFIX)


def stragglers(pids: set[int]) -> list[int]:
    """Processes of this scenario still running: those remembered and any other found in /proc."""
    found = {pid for pid in pids if alive(pid) and ours(pid)}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit() and alive(int(entry.name)) and ours(int(entry.name)):
            found.add(int(entry.name))
    return sorted(found)


def wait_gone(pids: set[int], timeout: float = 10.0) -> list[int]:
    """Demo robot processes of this scenario still running ``timeout`` s after the stack stopped
    (a dying gateway's children get SIGTERM from the kernel, a moment later)."""
    deadline = time.monotonic() + timeout
    while (left := stragglers(pids)) and time.monotonic() < deadline:
        time.sleep(0.25)
    return left


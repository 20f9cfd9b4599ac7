"""The migrated database every scenario starts from: the benchmark's operator and API token,
copied per scenario. On PostgreSQL, a template database on a cluster of the run's own."""
from __future__ import annotations

import shutil
from pathlib import Path

from tests.benchmarks.processes import DATABASE_URL_FILE, BenchError, environment, run_manage

USER, PASSWORD = "bench-operator", "bench-password-9431"
DATABASES = ("sqlite", "postgres")

SEED_USER = f"""
from django.contrib.auth import get_user_model
from django.contrib.auth.models import Group
user = get_user_model().objects.create_user({USER!r}, password={PASSWORD!r})
user.groups.add(Group.objects.get(name="operator"))
"""


class Template:
    """A migrated database with the benchmark's operator and API token, copied per scenario.
    On PostgreSQL it is a database on a cluster of the run's own, which ``close()`` removes."""

    def __init__(self, workdir: Path, database: str = "sqlite") -> None:
        if database not in DATABASES:
            raise BenchError(f"--database {database}: use one of {', '.join(DATABASES)}")
        self.dir = workdir / "template"
        self.dir.mkdir(parents=True)
        self.database = database
        self.cluster = None
        self._copies = 0
        if database == "postgres":
            from tests.postgres import Cluster

            self.cluster = Cluster()
        try:
            if self.cluster is not None:
                self._admin_url = self.cluster.start().rsplit("/", 1)[0] + "/postgres"
                self._create_database("bench_template")
            env = environment(self.dir, 0)
            run_manage(env, "migrate", "--noinput")
            run_manage(env, "shell", "-c", SEED_USER)
            # The token the way an operator makes one (docs/api.md).
            self.token = run_manage(env, "create_api_token", USER, "--name", "benchmark").strip()
        except BaseException:
            self.close()
            raise

    def copy_to(self, data_dir: Path) -> None:
        data_dir.mkdir(parents=True)
        if self.cluster is not None:
            self._copies += 1
            self._create_database(f"bench_{self._copies}", data_dir, template="bench_template")
        for path in self.dir.glob("db.sqlite3*"):
            shutil.copy(path, data_dir / path.name)
        shutil.copy(self.dir / "secret_key", data_dir / "secret_key")

    def _create_database(self, name: str, data_dir: Path | None = None, template: str | None = None) -> None:
        """A PostgreSQL database (a copy of ``template``), its URL written where
        ``database_url`` finds it."""
        import psycopg

        with psycopg.connect(self._admin_url, autocommit=True) as admin:
            admin.execute(f'CREATE DATABASE "{name}"' + (f' TEMPLATE "{template}"' if template else ""))
        url_file = (data_dir or self.dir) / DATABASE_URL_FILE
        url_file.touch(0o600)
        url_file.write_text(self._admin_url.rsplit("/", 1)[0] + f"/{name}\n")

    def close(self) -> None:
        """Stop and remove the PostgreSQL cluster, if any."""
        if self.cluster is not None:
            self.cluster.stop()
            self.cluster = None

"""The opt-in monitoring of docker/monitoring/: Prometheus and a provisioned Grafana dashboard.

- The Grafana files (the dashboard's JSON model, the data source and dashboard provider): what
  Grafana needs of them (ids, grid positions, a data source by uid on every panel and query, an
  expression in every query, the variables), and that they agree with one another and with the
  compose file's mounts.
- The compose override's profile "monitoring" (`docker-compose config`): opt-in, Grafana's
  password required, the token file mounted where prometheus.yml reads it, "web" an allowed host.
- Prometheus for real: Debian's prometheus 2.42 in the image docker/monitoring/Dockerfile builds
  (the compose service's image), `promtool check config` on docker/monitoring/prometheus.yml, and
  Prometheus with that file (only the target's port changed) scraping a real site (daphne, as
  `make demo` and the image serve it, with a fleet in its database: two gateways, one beating,
  robots with nodes, transitions, a mode, an alert, diagnostic statuses) with an API token from a
  file, as in compose. Then every query of every dashboard panel, its variables resolved from
  Prometheus as Grafana resolves them, returns data (a non-empty result, no NaN), both with the
  variables' real values and with "All".

Grafana itself is in neither Debian nor PyPI (compose takes Grafana's own image), so it does not
run here; Prometheus answers the dashboard's queries as it would answer Grafana's.
"""
from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
import yaml

from tests import stack
from tests.deploy import engine
from tests.deploy.engine import BASE_IMAGE, DOCKER_DIR, run
from tests.deploy.monitoring_support import (
    DASHBOARD,
    DATASOURCES,
    GATEWAY_ONLINE,
    GATEWAY_SILENT,
    GRAFANA_BUILTINS,
    LABEL,
    MONITORING_DIR,
    OVERRIDE,
    PROMETHEUS_IMAGE,
    PROMETHEUS_UID,
    PROMETHEUS_YML,
    PROVIDERS,
    ROBOT_A,
    ROBOT_B,
    SITE_TARGET,
    Beats,
    Prometheus,
    builtins,
    connects,
    dashboard,
    fleet,
    forget_fleet,
    load_yaml,
    query_panels,
    remove_leftovers,
    resolve_variables,
    scraped,
    substitute,
    variable_definition,
)


def test_dashboard_is_a_valid_provisioned_grafana_dashboard():
    model = dashboard()
    uid = load_yaml(DATASOURCES)["datasources"][0]["uid"]
    assert isinstance(model["schemaVersion"], int) and model["schemaVersion"] >= 36, "panels' datasource by uid"
    assert model["uid"] and len(model["uid"]) <= 40 and model["title"], "a fixed uid: links survive re-provisioning"
    assert model.get("id") is None, "a provisioned dashboard gets its id from Grafana"
    assert model["time"]["from"].startswith("now-") and model["time"]["to"] == "now"

    ids = [p["id"] for p in model["panels"]] + [p["id"] for r in model["panels"] if r["type"] == "row"
                                                 for p in r.get("panels", [])]
    assert all(isinstance(i, int) for i in ids) and len(ids) == len(set(ids)), f"panel ids unique: {ids}"
    boxes = []
    for panel in model["panels"]:
        grid = panel["gridPos"]
        assert set(grid) == {"h", "w", "x", "y"} and all(isinstance(v, int) for v in grid.values()), panel["title"]
        assert grid["w"] > 0 and grid["h"] > 0 and 0 <= grid["x"] and grid["x"] + grid["w"] <= 24, panel["title"]
        for other_title, other in boxes:
            overlap = (grid["x"] < other["x"] + other["w"] and other["x"] < grid["x"] + grid["w"]
                       and grid["y"] < other["y"] + other["h"] and other["y"] < grid["y"] + grid["h"])
            assert not overlap, f"{panel['title']!r} overlaps {other_title!r}"
        boxes.append((panel["title"], grid))
        if panel["type"] == "row":
            assert "targets" not in panel and "datasource" not in panel, f"row {panel['title']!r} has no queries"

    panels = query_panels(model)
    assert len(panels) >= 20, "a dashboard for a plant's monitoring team, not a sample"
    for panel in panels:
        where = f"panel {panel['id']} {panel['title']!r}"
        assert panel["type"] in {"stat", "timeseries", "table", "state-timeline", "bargauge", "gauge"}, where
        assert panel["title"] and panel.get("description"), f"{where}: says what it shows"
        assert panel["datasource"] == {"type": "prometheus", "uid": uid}, f"{where}: the provisioned data source"
        assert panel["targets"], f"{where}: has queries"
        refs = [t["refId"] for t in panel["targets"]]
        assert len(refs) == len(set(refs)), f"{where}: refIds unique"
        for query in panel["targets"]:
            assert query["datasource"] == panel["datasource"], f"{where} {query['refId']}: same data source"
            assert isinstance(query.get("expr"), str) and query["expr"].strip(), f"{where} {query['refId']}: expr"
            assert query["expr"].count("(") == query["expr"].count(")"), f"{where}: {query['expr']}"
        assert "fieldConfig" in panel and "options" in panel, where

    variables = {v["name"]: v for v in model["templating"]["list"]}
    assert {"gateway", "robot"} <= set(variables)
    for variable in variables.values():
        assert variable["type"] == "query" and variable["datasource"]["uid"] == uid, variable["name"]
        assert variable_definition(variable).startswith("label_values("), variable["name"]
        assert variable["refresh"] in (1, 2), f"{variable['name']}: its values are read from Prometheus"
    used = {name for p in panels for t in p["targets"] for name in re.findall(r"\$(\w+)", t["expr"])}
    assert used - set(variables) <= GRAFANA_BUILTINS, f"unknown variables: {used - set(variables) - GRAFANA_BUILTINS}"
    assert {"gateway", "robot"} <= used, "both variables filter panels"


def test_provisioning_files_agree_with_the_dashboard_and_compose():
    (source,) = load_yaml(DATASOURCES)["datasources"]
    assert load_yaml(DATASOURCES)["apiVersion"] == 1
    assert source["type"] == "prometheus" and source["access"] == "proxy" and source["uid"] == "lifecycle-prometheus"
    scrape = load_yaml(PROMETHEUS_YML)["scrape_configs"][0]
    assert source["jsonData"]["timeInterval"] == scrape["scrape_interval"] == "15s"
    url = urllib.parse.urlsplit(source["url"])
    override = load_yaml(OVERRIDE)["services"]
    assert url.hostname == "prometheus" and "prometheus" in override, "the compose service's name"
    assert any(p.endswith(f":{url.port}") for p in override["prometheus"]["ports"])
    assert set(override["grafana"]["networks"]) & set(override["prometheus"]["networks"]), "grafana reaches it"

    (provider,) = load_yaml(PROVIDERS)["providers"]
    assert load_yaml(PROVIDERS)["apiVersion"] == 1 and provider["type"] == "file"
    mounts = dict(v.removesuffix(":ro").split(":", 1) for v in override["grafana"]["volumes"] if v.endswith(":ro"))
    assert mounts["./monitoring/grafana/dashboards"] == provider["options"]["path"], "the provider reads the mount"
    assert mounts["./monitoring/grafana/provisioning"] == "/etc/grafana/provisioning"
    assert all(v.endswith(":ro") for v in override["grafana"]["volumes"] if isinstance(v, str)
               and v.startswith("./")), "Grafana cannot change the files it is given"
    assert sorted(p.name for p in DASHBOARD.parent.iterdir()) == ["lifecycle.json"]
    home = override["grafana"]["environment"]["GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH"]
    assert home == f"{provider['options']['path']}/{DASHBOARD.name}"


# ---------------------------------------------------------------------------------------
# The compose profile


def compose_config(tmp_path: Path, *args: str, password: str | None = "x" * 16) -> subprocess.CompletedProcess:
    """`docker-compose config` of the plain file with the monitoring override, in a copy of
    docker/ (no .env of this machine's), with none of the site's settings in the environment."""
    folder = tmp_path / "docker"
    if not folder.exists():
        shutil.copytree(DOCKER_DIR, folder, ignore=shutil.ignore_patterns("build", ".env", "*.token"))
    environment = {k: v for k, v in os.environ.items()
                   if not k.startswith(("REDIS_", "LIFECYCLE_", "DJANGO_", "GRAFANA_", "PROMETHEUS_"))}
    if password is not None:
        environment["GRAFANA_ADMIN_PASSWORD"] = password
    argv = ["docker-compose", "-f", "docker-compose.yml", "-f", "monitoring/docker-compose.monitoring.yml", *args]
    return run(argv, timeout=60, cwd=folder, env=environment, check=False)


def test_monitoring_profile_is_opt_in_and_takes_its_secrets_from_outside(docker_engine, tmp_path):
    refused = compose_config(tmp_path, "--profile", "monitoring", "config", "-q", password=None)
    assert refused.returncode != 0 and "GRAFANA_ADMIN_PASSWORD" in refused.stderr, refused.stderr
    answer = compose_config(tmp_path, "--profile", "monitoring", "config")
    assert answer.returncode == 0, answer.stderr
    merged = yaml.safe_load(answer.stdout)["services"]
    plain = load_yaml(DOCKER_DIR / "docker-compose.yml")["services"]
    assert set(merged) == set(plain) | {"prometheus", "grafana"}
    for name in ("prometheus", "grafana"):
        assert merged[name]["profiles"] == ["monitoring"], f"{name} starts only with --profile monitoring"
        assert "mem_limit" in merged[name] and merged[name]["restart"] == "unless-stopped", name
        assert all(p.startswith("127.0.0.1:") for p in merged[name]["ports"]), f"{name}: loopback by default"

    prometheus = merged["prometheus"]
    assert prometheus["image"] == PROMETHEUS_IMAGE, "the image this test builds and runs"
    assert Path(prometheus["build"]["context"]).name == "monitoring"
    assert prometheus["build"]["args"]["BASE_IMAGE"] == BASE_IMAGE
    scrape = load_yaml(PROMETHEUS_YML)["scrape_configs"][0]
    (token_mount,) = [v for v in prometheus["volumes"]
                      if isinstance(v, dict) and v["target"] == scrape["authorization"]["credentials_file"]]
    assert token_mount["type"] == "bind" and token_mount["read_only"] is True, "long form: no directory made for it"
    assert token_mount["source"] == str(tmp_path / "docker" / "monitoring" / "lifecycle.token")
    assert f"{tmp_path / 'docker' / 'monitoring' / 'prometheus.yml'}:/etc/prometheus/prometheus.yml:ro" in prometheus[
        "volumes"]
    assert "frontend" in prometheus["networks"] and "frontend" in merged["web"]["networks"], "it reaches web"
    (host, port), = [t.split(":") for t in scrape["static_configs"][0]["targets"]]
    assert host == "web" and port == "8000"
    allowed = merged["web"]["environment"]["DJANGO_ALLOWED_HOSTS"].split(",")
    assert allowed == plain["web"]["environment"]["DJANGO_ALLOWED_HOSTS"].split(":-")[1].rstrip("}").split(",") + [
        "web"], "the plain file's default, and the Host header Prometheus sends"
    grafana = merged["grafana"]
    assert grafana["image"].startswith("grafana/grafana:") and not grafana["image"].endswith(":latest")
    assert grafana["environment"]["GF_SECURITY_ADMIN_PASSWORD"] == "x" * 16, "from the environment"
    assert grafana["environment"]["GF_AUTH_ANONYMOUS_ENABLED"] == "false"
    assert (MONITORING_DIR / ".gitignore").read_text().count("*.token") == 1, "the token file is never committed"
    assert "!prometheus.yml" in (MONITORING_DIR / ".dockerignore").read_text(), "nor sent to a build"


# ---------------------------------------------------------------------------------------
# Prometheus against a real site


@pytest.fixture(scope="module")
def prometheus_image(docker_engine, timings) -> str:
    """The compose service's image: docker/monitoring/Dockerfile on the local base image
    (debootstrapped when absent, as build-images.sh does), Debian's prometheus in it."""
    if run(["docker", "image", "inspect", BASE_IMAGE], timeout=30, check=False).returncode != 0:
        assert BASE_IMAGE == "local/debian:bookworm", f"the base image {BASE_IMAGE} is not here"
        run([str(DOCKER_DIR / "build-base-image.sh")], timeout=600)
    with timings.timed("monitoring_image_build_s"):
        result = run(["docker", "build", "--pull=false", "--build-arg", f"BASE_IMAGE={BASE_IMAGE}",
                      "-t", PROMETHEUS_IMAGE, str(MONITORING_DIR)], timeout=900)
    engine.ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (engine.ARTIFACTS / "monitoring-image-build.log").write_text(result.stderr + result.stdout)
    answer = run(["docker", "run", "--rm", PROMETHEUS_IMAGE, "--version"], timeout=60)
    version = re.search(r"prometheus, version (\S+)", answer.stdout + answer.stderr)
    assert version, answer.stdout + answer.stderr
    timings.record("prometheus_version", version.group(1))
    return PROMETHEUS_IMAGE


@pytest.fixture(scope="module")
def monitored_site(prometheus_image, redis_server, live_db, scratch, timings):
    """A site (daphne) with a fleet, reached by a Prometheus container as "web" over a Docker
    network of the test's own (the site listens on this host's address there only), configured
    with docker/monitoring/prometheus.yml and a token file; Prometheus has scraped it twice, with
    transitions between the scrapes (so that rates and latency percentiles have values)."""
    from lifecycle_site.gateway_link import gateways

    remove_leftovers()
    workdir = scratch / "monitoring"
    workdir.mkdir()
    name = f"lcmon{os.getpid()}"
    site = beats = network = None
    try:
        made = fleet()
        beats = Beats()
        network = run(["docker", "network", "create", "--label", LABEL, name], timeout=60).stdout.strip()
        address = run(["docker", "network", "inspect", "-f", "{{(index .IPAM.Config 0).Gateway}}", name],
                      timeout=30).stdout.strip()
        assert re.fullmatch(r"\d+\.\d+\.\d+\.\d+", address), address
        port = stack.free_port()
        # As stack.start_site, on this host's address on the test's network (the Host header is "web").
        argv = [sys.executable, "-m", "lifecycle_site.serve", "-b", address, "-p", str(port),
                "lifecycle_site.asgi:application"]
        site = stack.Process("monitoring-site", argv, stack.environment(DJANGO_ALLOWED_HOSTS="localhost,127.0.0.1,web"),
                             stack.log_dir())
        stack.wait_for(lambda: connects(address, port) or not site.alive(), 30, "the site to listen")
        assert site.alive(), site.output()

        token_file = workdir / "lifecycle.token"
        token_file.write_text(made["token"])
        os.chown(token_file, PROMETHEUS_UID, PROMETHEUS_UID)
        token_file.chmod(0o400)
        config = load_yaml(PROMETHEUS_YML)
        scrape = config["scrape_configs"][0]
        assert scrape["static_configs"] == [{"targets": [SITE_TARGET]}]
        scrape["static_configs"] = [{"targets": [f"web:{port}"]}]  # the only change
        (workdir / "prometheus.yml").write_text(yaml.safe_dump(config, sort_keys=False))
        (workdir / "prometheus.yml").chmod(0o644)
        check = run(["docker", "run", "--rm", "--entrypoint", "promtool",
                     "-v", f"{workdir / 'prometheus.yml'}:/etc/prometheus/prometheus.yml:ro",
                     "-v", f"{token_file}:{scrape['authorization']['credentials_file']}:ro",
                     prometheus_image, "check", "config", "/etc/prometheus/prometheus.yml"], timeout=60, check=False)
        assert check.returncode == 0, check.stdout + check.stderr

        prometheus_port = stack.free_port()
        run([
            "docker", "run", "-d", "--name", f"{name}-prometheus", "--label", LABEL, "--network", name,
            "--add-host", f"web:{address}", "-p", f"127.0.0.1:{prometheus_port}:9090", "--memory", "512m",
            "-v", f"{workdir / 'prometheus.yml'}:/etc/prometheus/prometheus.yml:ro",
            "-v", f"{token_file}:{scrape['authorization']['credentials_file']}:ro",
            prometheus_image], timeout=60)
        prometheus = Prometheus(prometheus_port)
        began = time.monotonic()
        first = engine.wait_for(lambda: scraped(prometheus), 60, "Prometheus's first scrape of the site")
        # Counted on series the first scrape saw (a counter's first sample has nothing to increase from).
        made["transitions"](("succeeded", "api", 20.0), ("succeeded", "dashboard", 300.0), ("failed", "api", 2000.0))
        type(made["gateway"]).objects.filter(pk=made["gateway"].pk).update(logs_received=1500, facts_rejected=3)
        engine.wait_for(lambda: scraped(prometheus, after=first["lastScrape"]), 40, "the next scrape")
        timings.record("monitoring_two_scrapes_s", round(time.monotonic() - began, 1))
        # The dashboard's queries are evaluated just after that scrape, however long the tests
        # take: the rate windows then hold both scrapes, the transitions between them included.
        (last,) = prometheus.get("/api/v1/query", query='timestamp(up{job="lifecycle-manager"})')["result"]
        yield {"prometheus": prometheus, "site": site, "port": port, "address": address,
               "at": float(last["value"][1]) + 1}
    finally:
        if beats:
            beats.stop()
        if network:
            container = f"{name}-prometheus"
            logs = run(["docker", "logs", container], timeout=30, check=False)
            engine.ARTIFACTS.mkdir(parents=True, exist_ok=True)
            (engine.ARTIFACTS / "monitoring-prometheus.log").write_text(logs.stdout + logs.stderr)
            run(["docker", "rm", "-f", container], timeout=60, check=False)
        if site:
            site.stop()
        if network:
            run(["docker", "network", "rm", network], timeout=60, check=False)
        forget_fleet()
        gateways.forget()
        left = run(["docker", "ps", "-aq", "--filter", f"label={LABEL}"], timeout=30).stdout.split()
        left += run(["docker", "network", "ls", "-q", "--filter", f"label={LABEL}"], timeout=30).stdout.split()
        assert not left, f"the monitoring test left {left} in Docker"


def test_promtool_accepts_the_shipped_config_and_the_image_carries_it(prometheus_image, scratch):
    token = scratch / "promtool.token"
    token.write_text("a-token-of-the-operator")
    token.chmod(0o644)
    scrape = load_yaml(PROMETHEUS_YML)["scrape_configs"][0]
    inside = run(["docker", "run", "--rm", "--entrypoint", "cat", prometheus_image, "/etc/prometheus/prometheus.yml"],
                 timeout=60).stdout
    assert inside == PROMETHEUS_YML.read_text(), "the image's copy is docker/monitoring/prometheus.yml"
    check = run(["docker", "run", "--rm", "--entrypoint", "promtool",
                 "-v", f"{token}:{scrape['authorization']['credentials_file']}:ro",
                 prometheus_image, "check", "config", "/etc/prometheus/prometheus.yml"], timeout=60, check=False)
    assert check.returncode == 0 and "SUCCESS" in check.stdout + check.stderr, check.stdout + check.stderr
    # Without the operator's token file the configuration is refused, and says why.
    missing = run(["docker", "run", "--rm", "--entrypoint", "promtool", prometheus_image, "check", "config",
                   "/etc/prometheus/prometheus.yml"], timeout=60, check=False)
    assert missing.returncode != 0 and "lifecycle.token" in missing.stdout + missing.stderr
    user = run(["docker", "run", "--rm", "--entrypoint", "id", prometheus_image], timeout=60).stdout
    assert f"uid={PROMETHEUS_UID}(prometheus)" in user, "not root, and the uid the docs name for the token file"


def test_prometheus_scrapes_the_site_with_the_token(monitored_site):
    prometheus = monitored_site["prometheus"]
    target = prometheus.target()
    assert target["health"] == "up" and target["scrapeUrl"] == f"http://web:{monitored_site['port']}/metrics"
    (up,) = prometheus.get("/api/v1/query", query='up{job="lifecycle-manager"}')["result"]
    assert up["value"][1] == "1"
    (samples,) = prometheus.get("/api/v1/query", query='scrape_samples_scraped{job="lifecycle-manager"}')["result"]
    assert float(samples["value"][1]) > 50
    # Without the token the site refuses (the allow-list is empty): it is the token that lets Prometheus in.
    request = urllib.request.Request(f"http://{monitored_site['address']}:{monitored_site['port']}/metrics",
                                     headers={"Host": "web"})
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=10)
    assert refused.value.code == 401


def test_every_dashboard_query_returns_data(monitored_site):
    """Every target of every panel, with the variables' real values and with "All" (allValue):
    the query succeeds and its result has series, none of whose values is NaN."""
    prometheus = monitored_site["prometheus"]
    model = dashboard()
    interval = int(load_yaml(PROMETHEUS_YML)["scrape_configs"][0]["scrape_interval"].rstrip("s"))
    real = builtins(model, interval)
    options = resolve_variables(prometheus, model, real)
    assert {GATEWAY_ONLINE, GATEWAY_SILENT} <= set(options["gateway"]), "(and the gateway local of the migrations)"
    assert {ROBOT_A, ROBOT_B} <= set(options["robot"]), "(and robots other deploy tests of the run left)"
    everything = {**builtins(model, interval), **{v["name"]: v["allValue"] for v in model["templating"]["list"]}}
    empty, checked, answers = [], 0, []
    for panel in query_panels(model):
        for query in panel["targets"]:
            for what, values in (("values", real), ("All", everything)):
                expr = substitute(query["expr"], values)
                data = prometheus.get("/api/v1/query", query=expr, time=monitored_site["at"])
                checked += 1
                assert data["resultType"] == "vector", expr
                where = f"{panel['title']!r} {query['refId']} ({what}): {expr}"
                if not data["result"]:
                    empty.append(where)
                answers.append({"panel": panel["title"], "ref": query["refId"], "with": what, "expr": expr,
                                "series": {json.dumps(r["metric"], sort_keys=True): r["value"][1]
                                           for r in data["result"]}})
                nan = [s["metric"] for s in data["result"] if math.isnan(float(s["value"][1]))]
                assert not nan, f"{where}: NaN for {nan}"
    engine.ARTIFACTS.mkdir(parents=True, exist_ok=True)  # what each query gave, for a look after a failure
    (engine.ARTIFACTS / "monitoring-queries.json").write_text(json.dumps(answers, indent=1) + "\n")
    assert not empty, "queries without data:\n" + "\n".join(empty)
    assert checked >= 2 * 35


def test_the_dashboard_shows_every_family_the_site_exports(monitored_site):
    """A family added to /metrics without a panel fails here (docs/monitoring.md lists them)."""
    prometheus = monitored_site["prometheus"]
    exported = set(prometheus.get("/api/v1/label/__name__/values", **{"match[]": '{job="lifecycle-manager"}'}))
    exported = {n for n in exported if n.startswith("lifecycle_")}
    assert "lifecycle_diagnostic_statuses_not_kept_total" in exported and len(exported) >= 20, exported
    shown = " ".join(t["expr"] for p in query_panels(dashboard()) for t in p["targets"])
    missing = sorted(n for n in exported if not re.search(rf"\b{re.escape(n)}\b", shown))
    assert not missing, f"no panel shows {missing}"

# Fresh machine: `make demo` to try the product, `make test` to run the tests.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
# DDS discovery stays on this machine unless you say otherwise (see README).
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST

.PHONY: setup system-packages demo test test-postgres test-deploy bench images edge-package edge-cell-package translations clean

$(BIN)/.installed: requirements.txt requirements-dev.txt
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), "Python 3.11 is needed (the ROS 2 Jazzy wheels are built for it); set PYTHON=/path/to/python3.11"'
	@.ci/python-venv $(PYTHON)  # its ensurepip (Debian: python3.11-venv), installed or named
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -r requirements-dev.txt
	@touch $@

setup: $(BIN)/.installed

# The Debian packages the tests need (Redis, nginx, Chromium, Docker ...): installed when
# missing, as root or with passwordless sudo; otherwise it stops and prints the command to run.
# `make demo` does not need them.
system-packages:
	@.ci/system-packages

demo: setup
	$(BIN)/python manage.py run_demo

# The tests run in TEST_WORKERS pytest-xdist processes, a test file each at a time (its module's
# stack is started once), each worker a run of its own (tests/settings.py): 16 instead of 27
# minutes with 2 on a 2-core machine. TEST_WORKERS=0: all in one process (slower; the order in
# which pytest collects them).
TEST_WORKERS ?= 2
XDIST = $(if $(filter-out 0,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadfile)
test: system-packages setup
	$(BIN)/python -m pytest $(XDIST) --ignore=tests/deploy $(foreach m,$(POSTGRES_ONLY),--ignore=$(m)) $(PYTEST_ARGS)
	$(MAKE) --no-print-directory test-postgres

# The integration tests again with the site's database on PostgreSQL: a throw-away cluster of
# Debian's postgresql, started and removed by the run (tests/postgres.py), ~4 min. Left out:
# what is about DDS, TLS and process handling only, whose database use the others cover
# (network namespaces, DDS settings, Redis TLS, the demo's hard stop, a gateway killed,
# stopped or cut off by Redis, the two one-minute outages, processes found by their pid, probes
# of hung hosts, the gateway keeping desired states). Unit tests of what differs there:
# the log store (COPY) and values PostgreSQL refuses. A JUnit report asked for in PYTEST_ARGS
# goes to junit-postgres.xml beside the first run's. POSTGRES_ONLY: what concurrent
# transactions do to row locks, which SQLite (one writer at a time) does not have.
POSTGRES_LEAVE_OUT := test_networks test_dds_settings test_redis_tls test_demo_hard_stop test_killed_gateway_runs \
	test_run_verdicts test_stranger_gateway test_crash_local_processes test_liveness test_keep_desired
POSTGRES_DESELECT := test_gateways.py::test_nothing_is_lost_while_the_ingest_process_is_stopped_for_a_minute \
	test_gateways.py::test_a_gateway_that_loses_redis_for_a_minute_delivers_what_happened_meanwhile
POSTGRES_ONLY := tests/unit/test_fact_conflicts.py
test-postgres: system-packages setup
	LIFECYCLE_TEST_DATABASE=postgres $(BIN)/python -m pytest $(XDIST) tests/integration tests/unit/test_log_store.py \
		tests/unit/test_database_input.py $(POSTGRES_ONLY) \
		$(foreach m,$(POSTGRES_LEAVE_OUT),--ignore=tests/integration/$(m).py) \
		$(foreach t,$(POSTGRES_DESELECT),--deselect=tests/integration/$(t)) \
		$(subst junit.xml,junit-postgres.xml,$(PYTEST_ARGS))

# Real Docker engine: builds the images offline, runs the Industrial Edge compose file behind
# an nginx that serves it under a sub-path, as the device does (see docker/README.md).
test-deploy: system-packages setup
	$(BIN)/python -m pytest tests/deploy --timeout=2700 $(PYTEST_ARGS)  # building the images may take long on a fresh machine

# Container images (offline, from a wheelhouse) and the Industrial Edge app package.
images:
	docker/build-images.sh

edge-package:
	docker/edge/package.sh

edge-cell-package:
	docker/edge/package.sh --app edge-cell

# Speed and memory, measured side by side in one run (not part of `make test`).
bench: setup
	$(BIN)/python -m tests.benchmarks

# After marking text (docs/translation.md): the German catalogues brought up to date with every
# marked string (new ones empty, to be translated; parts under locale/de/parts/ merged in), then
# compiled. The .mo files are committed: running the product needs no gettext tools.
translations: setup
	@.ci/system-packages gettext
	$(BIN)/python -m tests.translations update

clean:
	rm -rf $(VENV) .pytest_cache tests/artifacts

# The two user commands: `make demo` and `make test`. Both create the virtual
# environment when it is missing and (re)install the project when
# pyproject.toml changed, so a fresh clone needs nothing else.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
RUN_DIR ?= runs/demo
# No telemetry from Rerun, ever; no window unless asked for.
export RERUN_ANALYTICS := 0
export TELEMETRY_ENABLED := false
export MUJOCO_GL ?= egl

.PHONY: demo test test-fast test-web chromium tmux lint venv clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	@# Rerun's analytics are switched off in its own settings, not by an environment variable;
	@# quietly: on a first run it prints its welcome banner before it obeys.
	@$(BIN)/rerun analytics disable >/dev/null 2>&1 \
		|| echo "note: rerun analytics disable failed; RERUN_ANALYTICS=0 still applies to every run" >&2
	@touch $(STAMP)

# The teleoperation demo: every service under supervisord, the scripted operator
# grasps the cube and drops it in the bin, headless, in real time (the bus at
# loop.rate_hz, physics and force rendering at 1 kHz inside their processes); its verdict
# says whether the machine kept real time (exit code 3 when it lost it).
# `make demo DEMO_MODE=lockstep`: the same run for every user on every machine.
DEMO_MODE ?= realtime
demo: $(STAMP)
	@mkdir -p $(RUN_DIR)
	$(BIN)/teleop run grasp --mode $(DEMO_MODE) --seed 0 --run-dir $(RUN_DIR) \
		--rrd $(RUN_DIR)/recording.rrd --summary-json $(RUN_DIR)/summary.json

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# The web viewer's screenshot test needs Chromium: install it if we can (root, Debian);
# without it that test checks the page is served and skips the screenshot.
# The unit layer (no bus, no processes) on every core; the integration layer (real
# sessions, each test waiting on tokens and samples, never on the clock) two files at a
# time; then the e2e layer one test at a time, as its stacks need the cores to themselves.
INTEGRATION := $(BIN)/python -m pytest tests/integration -n 2 --dist loadfile
test: lint
	-@test -x $(CHROMIUM) || $(MAKE) --no-print-directory chromium
	@command -v tmux >/dev/null || $(MAKE) --no-print-directory tmux
	$(BIN)/python -m pytest tests/unit -n auto
	$(INTEGRATION)
	$(BIN)/python -m pytest tests/e2e

# The unit and integration layers only (no supervisord stacks): a minute or so.
test-fast: lint
	$(BIN)/python -m pytest tests/unit -n auto
	$(INTEGRATION)

# Debian's Chromium, for the headless screenshot of the web viewer served by --web.
# `make test` installs it when it can and runs the screenshot test when it is there (else
# the test checks the page is served and skips the screenshot); `make test-web` requires it.
CHROMIUM ?= /usr/bin/chromium
$(CHROMIUM):
	apt-get update
	apt-get install -y --no-install-recommends chromium

chromium: $(CHROMIUM)

# tmux: the keyboard operator's end-to-end test types into a real terminal through it
# (tests/e2e/test_keyboard.py). `make test` installs it when it is missing (root, Debian).
tmux:
	apt-get update
	apt-get install -y --no-install-recommends tmux

test-web: $(STAMP) $(CHROMIUM)
	TELEOP_REQUIRE_CHROMIUM=1 $(BIN)/python -m pytest tests/e2e/test_viewer.py

clean:
	rm -rf runs .pytest_cache

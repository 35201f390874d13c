# Two commands on a fresh machine: `make demo` and `make test`.
# Both create .venv and install what they need when it is missing.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

NODE_STAMP := tests/js/node_modules/.package-lock.json

.PHONY: demo test bench venv clean system-packages system-deps lint lint-imports slim test-lowest fresh-check docs

venv: $(STAMP)

# uv resolves and installs the test environment in parallel (a fifth of pip's time on two cores);
# the edge box's own install (slim) stays pip's, as a user's would be.
# Bytecode is compiled at install, as pip does and uv does only when asked: where Python writes
# no .pyc of its own (PYTHONDONTWRITEBYTECODE), every process would compile what it imports again
# (pandas, scipy.signal and statsmodels: 15 s of CPU per process that fits, 2.5 s compiled).
COMPILE_OWN := $(PY) -m compileall -q -j 0 compensator cnc_adapters calibration machine_sim thermocomp
$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check 'uv>=0.5'
	$(VENV)/bin/uv pip install --quiet --compile-bytecode --python $(PY) -e '.[all,test,docs]'
	$(COMPILE_OWN) >/dev/null
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/thermocomp demo --output-dir demo-output

system-packages:
	bash scripts/system-deps.sh packages

system-deps: system-packages
	bash scripts/system-deps.sh linuxcnc

lint-imports: $(STAMP)
	$(VENV)/bin/lint-imports

# ruff's rules and format, the import contracts, mypy (configured in pyproject.toml). Each runs
# whatever the one before found, so one run shows every finding; any finding fails the target.
lint: $(STAMP)
	@status=0; \
	for tool in 'ruff check .' 'ruff format --check .' lint-imports mypy; do \
		echo "lint: $$tool"; $(VENV)/bin/$$tool || status=1; \
	done; \
	exit $$status

# the edge box's install, without extras (tests/test_slim_install.py measures and runs it)
slim:
	bash scripts/slim-venv.sh

# three workers on two cores (pytest-xdist; the tests are independent: free loopback ports, their
# own temporary directories, one HAL at a time by a lock): a sixth of the suite's time waits on
# servers and child processes, and the third worker fills it.
# A worker that is free takes tests from a busy one. PYTEST_WORKERS=0 runs them in this process.
PYTEST_WORKERS ?= 3
XDIST := $(if $(filter 0,$(PYTEST_WORKERS)),,-n $(PYTEST_WORKERS) --dist worksteal)

# .venv (uv) and the Debian packages (apt) install at the same time; the environments that
# build this checkout (slim, LinuxCNC) one after the other, as they share ./build
test:
	$(MAKE) --no-print-directory -j2 $(STAMP) system-packages
	$(MAKE) --no-print-directory system-deps lint slim
	$(PY) -m pytest -q $(XDIST)

# The oldest versions pyproject.toml allows (uv's lowest-direct resolution: every direct
# dependency at its lower bound), and the tests that exercise them: each library's own API
# (numpy, pydantic, asyncua, pymodbus, pyserial, prometheus_client, paho-mqtt, scipy,
# statsmodels, pandas, matplotlib, rich, python-snap7, pyads).
LOWEST := .venv-lowest
# One or two modules per library, those that call its API directly; the modules that reach the
# same calls through more of this project's code (the chiller's links, the controls' routes,
# bad-cell replays, runtime trust) are left to `make test`. Of the command line's tests, those
# that fit, replay, plot and read model files (pandas, statsmodels, scipy, matplotlib, rich,
# pydantic); its bad-input cases check this project's messages, not a library's.
CLI := tests/test_cli.py::test_
LOWEST_TESTS ?= tests/test_io.py tests/test_model.py tests/test_adapters.py \
	tests/test_adapter_settings.py tests/test_control_plc.py \
	$(CLI)fit_writes_a_loadable_model_and_a_json_report $(CLI)fit_human_report_names_the_winner_and_the_reference \
	$(CLI)replay_json_keys_and_outputs $(CLI)replay_without_measurement_has_null_residuals_and_warns_out_of_range \
	$(CLI)bad_model_files $(CLI)model_command_shows_schema_and_a_model \
	$(CLI)replay_applies_the_runtimes_shaping_and_compares_the_policies \
	tests/test_stability.py tests/test_ident.py tests/test_tuning.py \
	tests/test_opcua_security.py tests/test_wizard.py::test_wizard_imports_daq_logs \
	tests/test_status.py tests/test_mqtt.py

$(LOWEST)/.stamp: pyproject.toml $(STAMP)
	rm -rf $(LOWEST)
	$(VENV)/bin/uv venv --quiet --python $(PYTHON) $(LOWEST)
	$(VENV)/bin/uv pip install --quiet --compile-bytecode --python $(LOWEST)/bin/python \
		--resolution lowest-direct -e '.[calibration,plc,ads,test,docs]'
	touch $@

test-lowest: $(LOWEST)/.stamp system-deps
	$(LOWEST)/bin/python scripts/check-lowest.py
	$(LOWEST)/bin/python -m pytest -q -p no:cacheprovider $(XDIST) $(LOWEST_TESTS)

# CI as a new machine runs it, RUNS times in a row (root: it removes what the project created
# outside the clone first; scripts/fresh-check.sh says what)
RUNS ?= 1
fresh-check:
	bash scripts/fresh-check.sh $(RUNS)

# The documentation site (mkdocs.yml, docs/): strict, so a broken link or anchor fails the build
# (tests/test_docs.py runs the same build in `make test`); the result opens from build/site/index.html
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict --quiet -d build/site

bench: $(STAMP)
	$(PY) bench/run_all.py

clean:
	rm -rf $(VENV) .venv-slim $(LOWEST) demo-output .pytest_cache .hypothesis tests/js/node_modules build *.egg-info \
		.mypy_cache .ruff_cache .import_linter_cache

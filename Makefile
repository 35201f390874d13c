# Two commands on a fresh machine: `make demo` and `make test`.
# Both create .venv and install what they need when it is missing.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

NODE_STAMP := tests/js/node_modules/.package-lock.json

.PHONY: demo test bench venv clean system-deps lint-imports slim

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[all,test]'
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/thermocomp demo --output-dir demo-output

system-deps:
	bash scripts/system-deps.sh

lint-imports: $(STAMP)
	$(VENV)/bin/lint-imports

# the edge box's install, without extras (tests/test_slim_install.py measures and runs it)
slim:
	bash scripts/slim-venv.sh

test: $(STAMP) system-deps lint-imports slim
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/run_all.py

clean:
	rm -rf $(VENV) .venv-slim demo-output .pytest_cache .hypothesis tests/js/node_modules build *.egg-info

# Two commands on a fresh machine: `make demo` and `make test`.
# Both create .venv and install what they need when it is missing.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

NODE_STAMP := tests/js/node_modules/.package-lock.json

.PHONY: demo test bench venv clean system-deps lint-imports

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

test: $(STAMP) system-deps lint-imports
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/run_all.py

clean:
	rm -rf $(VENV) demo-output .pytest_cache .hypothesis tests/js/node_modules build *.egg-info

#!/usr/bin/env bash
# The edge box's install: `pip install thermocomp` with no extras, in .venv-slim (or $1).
# The venv has no pip or setuptools of its own (25 MB that the service never uses): this
# Python's pip installs into it (`pip --python`), as uv or a deployment image would.
# The dependencies are installed once per change of pyproject.toml's dependency list (by content,
# not by the files' dates); this checkout's code every time (not editable: what a user's pip would
# put there). Prints the venv's size.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${1:-.venv-slim}"
python="${PYTHON:-python3}"
# pip's output less the notes this machine's pip configuration adds; pip's exit status stays the
# pipeline's (pipefail), so a failed install fails the script
quiet_pip() { grep -v "^WARNING: Location" || true; }
want="$("$python" -c '
import json, sys, tomllib
p = tomllib.load(open("pyproject.toml", "rb"))["project"]
print(sys.version.split()[0], json.dumps(p["dependencies"]))
' | sha256sum | cut -c1-32)"
rm -rf build ./*.egg-info  # setuptools would carry modules this checkout has since removed
if [ ! -x "$venv/bin/python" ] || [ "$(cat "$venv/.deps-stamp" 2>/dev/null)" != "$want" ]; then
  rm -rf "$venv"
  "$python" -m venv --without-pip "$venv"
  # the dependencies by uv when make test installed it (the same packages, a fifth of the time)
  if [ -x .venv/bin/uv ]; then
    .venv/bin/uv pip install --quiet --python "$venv/bin/python" .
  else
    "$python" -m pip --python "$venv/bin/python" install --quiet --disable-pip-version-check --no-cache-dir . 2>&1 | quiet_pip
  fi
  echo "$want" > "$venv/.deps-stamp"
fi
"$python" -m pip --python "$venv/bin/python" install --quiet --disable-pip-version-check --no-cache-dir --no-deps --force-reinstall . \
  2>&1 | quiet_pip
rm -rf build ./*.egg-info
"$venv/bin/thermocomp" --version >/dev/null
echo "slim-venv: $venv $(du -sm "$venv" | cut -f1) MB"

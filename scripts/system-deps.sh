#!/usr/bin/env bash
# Install what the test suite needs from outside PyPI:
# - Node.js and npm (the independent OPC UA implementation, node-opcua), and the npm packages
#   pinned in tests/js;
# - socat (pseudo-terminal pairs for the serial links);
# - Chromium (Debian's `chromium`, /usr/bin/chromium) for the status page's browser test, driven by
#   playwright-core from tests/js (Playwright's own browsers are never downloaded);
# - mosquitto (the MQTT broker tests/test_mqtt.py starts on a free loopback port; the package's
#   own service, if systemd starts it, is not used);
# - LinuxCNC (Debian's linuxcnc-uspace) for the LinuxCNC integration tests, and a virtual
#   environment on Debian's own python3 that sees LinuxCNC's `hal` and `linuxcnc` modules
#   (--system-site-packages), from which LinuxCNC starts `thermocomp` as a HAL component.
#   rtapi refuses to run as root, so as root a system user `thermocomp-ci` is created to run it
#   and the environment goes to /opt/thermocomp/linuxcnc-venv (readable by that user).
#
#   scripts/system-deps.sh [packages|linuxcnc]   (default: both, in that order)
# `packages`: the Debian and npm packages; `linuxcnc`: the LinuxCNC environment (needs the first).
set -euo pipefail
cd "$(dirname "$0")/.."
phase="${1:-all}"
case "$phase" in all|packages|linuxcnc) ;; *) echo "system-deps: usage: $0 [packages|linuxcnc]" >&2; exit 2 ;; esac

root=0
[ "$(id -u)" -eq 0 ] && root=1

# pip's output less the notes this machine's pip configuration adds; pip's own exit status
# stays the pipeline's (pipefail), so a failed install fails the script
quiet_pip() { grep -v "^WARNING: Location" || true; }
if [ "$phase" != linuxcnc ]; then
  need=()
  command -v node >/dev/null 2>&1 || need+=(nodejs)
  command -v npm >/dev/null 2>&1 || need+=(npm)
  command -v socat >/dev/null 2>&1 || need+=(socat)
  [ -x /usr/sbin/mosquitto ] || need+=(mosquitto)  # /usr/sbin: not on a user's PATH
  optional=()
  command -v linuxcnc >/dev/null 2>&1 || optional+=(linuxcnc-uspace)
  [ -x /usr/bin/chromium ] || optional+=(chromium)
  /usr/bin/python3 -c 'import ensurepip, venv' >/dev/null 2>&1 || optional+=(python3-venv)
  if [ $root -eq 1 ]; then
    need+=("${optional[@]}")
    optional=()
  fi
  if [ ${#need[@]} -gt 0 ]; then
    if [ $root -eq 1 ]; then
      apt-get update -qq
      DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >/dev/null
    else
      echo "system-deps: missing ${need[*]}; run as root or: sudo apt-get install ${need[*]}" >&2
      exit 1
    fi
  fi
  if [ ${#optional[@]} -gt 0 ]; then
    echo "system-deps: ${optional[*]} missing: the LinuxCNC or status page tests will be skipped" \
         "(sudo apt-get install --no-install-recommends ${optional[*]})" >&2
  fi

  if [ ! -f tests/js/node_modules/.package-lock.json ] || [ tests/js/package-lock.json -nt tests/js/node_modules/.package-lock.json ]; then
    npm ci --prefix tests/js --no-audit --no-fund --loglevel=error
  fi
fi
[ "$phase" = packages ] && exit 0

if command -v linuxcnc >/dev/null 2>&1 && /usr/bin/python3 -c 'import ensurepip, venv' >/dev/null 2>&1; then
  if [ $root -eq 1 ]; then
    id thermocomp-ci >/dev/null 2>&1 || useradd --system --create-home --shell /usr/sbin/nologin thermocomp-ci
    lvenv=/opt/thermocomp/linuxcnc-venv
  else
    lvenv="$PWD/.venv-linuxcnc"
  fi
  # What the LinuxCNC tests import there: the runtime (the HAL component) and the calibration
  # extra (`thermocomp hal-plant`, run logs). A test environment, not the edge box's slim install.
  extras=calibration
  # The install this needs, as content: Debian's Python, the extras and pyproject's dependency
  # lists. Any change rebuilds the environment, whatever the files' dates say.
  want="$(/usr/bin/python3 -c '
import json, sys, tomllib
p = tomllib.load(open("pyproject.toml", "rb"))["project"]
print(sys.version.split()[0], sys.argv[1], json.dumps([p["dependencies"], p["optional-dependencies"]], sort_keys=True))
' "$extras" | sha256sum | cut -c1-32)"
  imports="import hal, linuxcnc, compensator, calibration, scipy, pandas"
  # setuptools builds in ./build and would carry modules this checkout has since removed
  rm -rf build ./*.egg-info
  if [ "$(cat "$lvenv/.deps-stamp" 2>/dev/null)" != "$want" ] \
      || ! "$lvenv/bin/python" -c "$imports" >/dev/null 2>&1; then
    echo "system-deps: building the LinuxCNC environment in $lvenv ($extras)" >&2
    rm -rf "$lvenv"
    /usr/bin/python3 -m venv --system-site-packages "$lvenv"
    # uv (make test installs it in .venv first) takes a fifth of pip's time; pip without it
    if [ -x .venv/bin/uv ]; then
      .venv/bin/uv pip install --quiet --compile-bytecode --python "$lvenv/bin/python" ".[$extras]"
    else
      "$lvenv/bin/pip" install --quiet --disable-pip-version-check ".[$extras]" 2>&1 | quiet_pip
    fi
    echo "$want" > "$lvenv/.deps-stamp"
  fi
  # this checkout's code, every time (dependencies as above)
  "$lvenv/bin/pip" install --quiet --disable-pip-version-check --no-deps --force-reinstall . 2>&1 | quiet_pip
  rm -rf build ./*.egg-info
  if ! "$lvenv/bin/python" -c "$imports"; then
    echo "system-deps: the LinuxCNC environment $lvenv cannot import what the tests need" >&2
    exit 1
  fi
  [ $root -eq 1 ] && chmod -R a+rX /opt/thermocomp
fi
exit 0

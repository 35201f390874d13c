#!/usr/bin/env bash
# CI as a new machine runs it: remove everything the project ever created outside a clone, clone
# this checkout's HEAD into a temporary directory, and run `CI=true bash .ci/run` there; RUNS times
# in a row (default 1), each after a new removal. Prints each run's exit status, wall time and
# pytest's closing lines; exits non-zero if any run failed.
#
#   scripts/fresh-check.sh [RUNS] [--keep-packages] [--keep-caches]   (`make fresh-check`)
#
# Removed before each run:
# - processes left by an interrupted earlier check (whose working directory is a fresh clone);
# - /opt/thermocomp (the LinuxCNC environment) and the thermocomp-ci user with its home;
# - in this checkout: .venv*, tests/js/node_modules, build/, *.egg-info, demo-output;
# - the Debian packages scripts/system-deps.sh installs (linuxcnc-uspace, chromium, mosquitto,
#   socat), unless --keep-packages: a new machine has none of them;
# - pip's, uv's and npm's caches, unless --keep-caches.
# Committed work only: uncommitted changes are not in the clone (the script says so).
set -euo pipefail
cd "$(dirname "$0")/.."
src=$PWD

runs=1
keep_packages=0
keep_caches=0
for arg in "$@"; do
  case "$arg" in
    --keep-packages) keep_packages=1 ;;
    --keep-caches) keep_caches=1 ;;
    ''|*[!0-9]*) echo "fresh-check: usage: $0 [RUNS] [--keep-packages] [--keep-caches]" >&2; exit 2 ;;
    *) runs=$arg ;;
  esac
done
if [ "$(id -u)" -ne 0 ]; then
  echo "fresh-check: run as root: it removes /opt/thermocomp, a system user and Debian packages" >&2
  exit 2
fi
if [ -n "$(git status --porcelain --untracked-files=no)" ]; then
  echo "fresh-check: note: uncommitted changes are not checked, only HEAD $(git rev-parse --short HEAD)" >&2
fi

# what an interrupted earlier run left behind: its pytest workers' command lines do not name the
# clone, their working directory does
kill_leftovers() {
  local pid cwd
  for pid in $(ls /proc | grep -E '^[0-9]+$'); do
    cwd=$(readlink "/proc/$pid/cwd" 2>/dev/null) || continue
    case "$cwd" in /tmp/thermocomp-fresh.*) kill -9 "$pid" 2>/dev/null || true ;; esac
  done
}

remove_state() {
  kill_leftovers
  pkill -u thermocomp-ci >/dev/null 2>&1 || true  # a LinuxCNC left running by an interrupted test
  sleep 0.5
  rm -rf /opt/thermocomp
  if id thermocomp-ci >/dev/null 2>&1; then
    userdel --remove thermocomp-ci >/dev/null 2>&1 || userdel thermocomp-ci
  fi
  rm -rf /home/thermocomp-ci
  rm -rf "$src"/.venv "$src"/.venv-* "$src"/tests/js/node_modules "$src"/build "$src"/*.egg-info \
         "$src"/demo-output
  if [ $keep_caches -eq 0 ]; then
    rm -rf "$HOME/.cache/pip" "$HOME/.cache/uv" "$HOME/.npm"
  fi
  if [ $keep_packages -eq 0 ]; then
    local installed=()
    for pkg in linuxcnc-uspace chromium chromium-common mosquitto socat; do
      dpkg -s "$pkg" >/dev/null 2>&1 && installed+=("$pkg")
    done
    if [ ${#installed[@]} -gt 0 ]; then
      DEBIAN_FRONTEND=noninteractive apt-get purge -y -qq "${installed[@]}" >/dev/null
      DEBIAN_FRONTEND=noninteractive apt-get autoremove -y -qq --purge >/dev/null
    fi
  fi
}

failed=0
summary=()
for i in $(seq 1 "$runs"); do
  remove_state
  clone=$(mktemp -d /tmp/thermocomp-fresh.XXXXXX)
  log="/tmp/thermocomp-fresh-$i.log"
  git clone --quiet "$src" "$clone"
  echo "fresh-check: run $i of $runs: $(git -C "$clone" rev-parse --short HEAD) in $clone (log: $log)"
  start=$(date +%s)
  set +e
  # its own session, so that an interrupted check takes the whole run down with it
  setsid bash -c 'cd "$1" && CI=true exec bash .ci/run </dev/null' _ "$clone" >"$log" 2>&1 &
  run_pid=$!
  trap 'kill -- -"$run_pid" 2>/dev/null; kill_leftovers; exit 130' INT TERM
  wait "$run_pid"
  rc=$?
  trap - INT TERM
  set -e
  wall=$(( $(date +%s) - start ))
  counts=$(grep -E "^(=+ )?[0-9]+ (passed|failed)|^[0-9]+ (passed|failed|error)" "$log" | sed 's/=//g; s/^ *//; s/ *$//' | paste -sd ';' -)
  line="run $i: exit $rc, $((wall / 60)) min $((wall % 60)) s; ${counts:-no pytest summary}"
  echo "fresh-check: $line"
  summary+=("$line")
  [ $rc -eq 0 ] || failed=1
  rm -rf "$clone"
done
printf 'fresh-check: %s\n' "${summary[@]}"
exit $failed

#!/usr/bin/env bash
# The optional Debian packages (scripts/setup.sh runs this): ROS 2 itself is not installable
# here, but python3-rosidl, rosidl-tools, colcon, python3-colcon-ros and python3-catkin-pkg carry
# the same .msg parser, package.xml validator and colcon that a ROS build runs, so the tests can
# check those files; libllvm19 is the LLVM that Sionna RT's Dr.Jit runs on (the ray-traced
# channel; deepsync finds it by itself). Without them (no root, no apt, the package lock held
# too long, no network) those tests skip, and this says so; it never stops the setup.
#   DEEPSYNC_APT_WAIT   seconds to wait for another package manager's lock (default 300)
set -uo pipefail

PACKAGES="python3-rosidl rosidl-tools colcon python3-colcon-ros python3-catkin-pkg libllvm19"
WAIT=${DEEPSYNC_APT_WAIT:-300}
RETRY=${DEEPSYNC_APT_RETRY:-5}  # seconds between two tries while the lock is held

command -v dpkg-query >/dev/null || exit 0  # not Debian or Ubuntu: nothing to check
missing=""
for p in $PACKAGES; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
[ -n "$missing" ] || exit 0

skip() {
  echo "setup: skipping the optional Debian packages ($1); the ROS-tooling and ray-tracing tests will skip."
  echo "setup: to add them later: apt-get install$missing (then rerun scripts/setup.sh)"
  exit 0
}

command -v apt-get >/dev/null || skip "no apt-get"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then
  command -v sudo >/dev/null || skip "installing them needs root or sudo"
  if sudo -n true 2>/dev/null; then
    SUDO="sudo -n"
  elif [ -t 0 ]; then
    SUDO="sudo"
  else
    skip "sudo asks for a password and there is no terminal to type it"
  fi
fi

echo "setup: the ROS-tooling and ray-tracing tests use Debian's$missing"
echo "setup: (the .msg parser, package.xml validator and colcon of a ROS build; LLVM for Sionna RT); installing them with"
echo "setup: apt-get update and apt-get install, as $([ -z "$SUDO" ] && echo root || echo "root through sudo")"
if [ "$SUDO" = sudo ]; then
  sudo -v || skip "sudo refused"  # its password asked once, here, not in the middle of apt's output
fi

# apt's own error when another apt or dpkg (unattended-upgrades, a software centre) holds the
# lock: wait for it, a bounded time, saying so; any other failure skips the packages
apt_get() {
  local deadline=$((SECONDS + WAIT)) said="" output
  while true; do
    if output=$($SUDO env DEBIAN_FRONTEND=noninteractive apt-get -q "$@" 2>&1); then
      return 0
    fi
    if ! grep -qiE "could not get lock|unable to acquire|is held by process|lock-frontend" <<<"$output"; then
      echo "$output" | tail -n 3 | sed 's/^/setup:   apt-get: /'
      skip "apt-get $1 failed"
    fi
    if [ "$SECONDS" -ge "$deadline" ]; then
      skip "another package manager still holds the dpkg lock after ${WAIT} s (DEEPSYNC_APT_WAIT)"
    fi
    if [ -z "$said" ]; then
      holder=$(grep -oiE "held by process [0-9]+ \([^)]*\)" <<<"$output" | head -n 1)
      echo "setup: another package manager holds the dpkg lock${holder:+ ($holder)}; waiting up to ${WAIT} s for it"
      said=1
    fi
    sleep "$RETRY"
  done
}

echo "setup: apt-get update (the package lists)"
apt_get update
echo "setup: apt-get install$missing"
apt_get install -y $missing
echo "setup: Debian packages installed"

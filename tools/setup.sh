#!/bin/sh
# Install rtloop for this checkout: Debian/Ubuntu packages, then a virtual environment in .venv
# with every extra and the test tools. Works as root (no sudo needed) and as a user with sudo.
#
#   tools/setup.sh            # system packages + .venv with rtloop[all,test]
#   tools/setup.sh --no-apt   # only the virtual environment (packages already there)
set -eu
cd "$(dirname "$0")/.."

packages="python3-venv python3-dev gcc g++ libatomic1 util-linux rt-tests stress-ng"

if [ "${1:-}" != "--no-apt" ]; then
    if ! command -v apt-get >/dev/null 2>&1; then
        echo "tools/setup.sh: no apt-get here; install these yourself, then run tools/setup.sh --no-apt:" >&2
        echo "  $packages" >&2
        exit 2
    fi
    echo "tools/setup.sh: installing system packages (apt-get): $packages"  # quiet below: one line per step
    # Wait for another apt (a fresh Ubuntu's unattended-upgrades, a second setup) instead of failing on its lock.
    apt_wait="-o DPkg::Lock::Timeout=300"
    # shellcheck disable=SC2086  # one word per option and per package
    tools/as-root env DEBIAN_FRONTEND=noninteractive apt-get $apt_wait update -qq
    # shellcheck disable=SC2086
    tools/as-root env DEBIAN_FRONTEND=noninteractive apt-get $apt_wait install -y -qq $packages >/dev/null
fi

echo "tools/setup.sh: creating .venv and installing rtloop[all,test] in it (a few minutes the first time)"
python3 -m venv .venv
.venv/bin/pip install -q --upgrade pip 'setuptools>=77'  # setup.py build_ext (tests) reads the SPDX license string
.venv/bin/pip install -q -e '.[all,test]'
# Bytecode now, as the user: runs through sudo (tools/as-root) read it and write none.
.venv/bin/python -m compileall -q src examples tests >/dev/null || true
echo "rtloop installed in .venv: .venv/bin/rtloop (real-time runs need root: tools/as-root .venv/bin/rtloop run ...)"

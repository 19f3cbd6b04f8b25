#!/usr/bin/env bash
# Peer tests of the virtual board: python-canopen + python-can (slcan over
# TCP) against `perpend board`. Creates/uses host-tests/peer/.venv
# (gitignored), installs the pinned requirements, builds the `perpend`
# binary and runs pytest. Extra arguments go to pytest (e.g. -k aborts).
#
#   host-tests/peer/run.sh            # from anywhere
#   PYTHON=python3.11 host-tests/peer/run.sh -x
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
venv="$here/.venv"

if [ ! -x "$venv/bin/python" ]; then
    "${PYTHON:-python3}" -m venv "$venv"
fi
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$here/requirements.txt"

# PERPEND_BIN set (CI: the binary `cargo xtask test` built): used as is.
if [ -z "${PERPEND_BIN:-}" ]; then
    (cd "$root" && cargo build --quiet -p perpend-cli --bin perpend)
    target="${CARGO_TARGET_DIR:-$root/target}"
    case "$target" in /*) ;; *) target="$root/$target" ;; esac
    export PERPEND_BIN="$target/debug/perpend"
fi

cd "$here"
exec "$venv/bin/python" -m pytest -q -p no:cacheprovider "$@"

#!/usr/bin/env bash
# The blind diagnosis check: runs written by host-tests/blind/gen.py (an
# independent generator, Python standard library only, sharing no code with
# perpend) diagnosed by `perpend diagnose --json`, scored by score.py against
# the hidden truth, through `perpend bench diagnose` (the debug build).
# Default: the reduced grid CI runs, with its pooled goals (exit 1 on a
# miss). `run.sh --full --md FILE` runs the whole grid of docs/diagnosis.md;
# other options are those of `perpend bench diagnose --help`.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
(cd "$root" && cargo build --quiet -p perpend-cli --bin perpend)
target="${CARGO_TARGET_DIR:-$root/target}"
case "$target" in /*) ;; *) target="$root/$target" ;; esac
if [ "${1:-}" = "--full" ]; then
    exec "$target/debug/perpend" bench diagnose --blind "$here" "$@"
fi
case " $* " in *" --check "*) exec "$target/debug/perpend" bench diagnose --blind "$here" "$@" ;; esac
exec "$target/debug/perpend" bench diagnose --blind "$here" --check "$@"

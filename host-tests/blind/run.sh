#!/usr/bin/env bash
# The blind diagnosis check: runs written by host-tests/blind/gen.py (an
# independent generator, Python standard library only, sharing no code with
# perpend) diagnosed by `perpend diagnose --json`, scored by score.py against
# the hidden truth, through `perpend bench diagnose` (the debug build).
# Default: the reduced grid CI runs, with its pooled goals (exit 1 on a
# miss). `run.sh --full --md FILE` runs the whole grid of docs/diagnosis.md;
# other options are those of `perpend bench diagnose --help`.
# `run.sh --v3 [--quick] [--check] [--seed-base N] [--nulls N] [--effects N] [--md FILE]`
# runs the v3 block instead (v3.py: the cases of issue 35 — incidence spot,
# gain on two sensors at 30 um, drift + warm-up with and without a plateau,
# hysteresis — graded by what they cost the calibrated normal): score.py
# directly, since `perpend bench diagnose` has no option for it. CI runs
# `--v3 --quick --check` (70 runs, goals pooled: v3.py pooled_check) as a
# step of its own; the whole block (290 runs) is docs/diagnosis.md's.
# `run.sh --power [power.py's options]` runs the diagnosis beside the
# oracle (power.py, oracle.py: issue 46): the full comparison of
# docs/diagnosis.md ("Power against the oracle") is
# `run.sh --power --runs 5 --nulls 16 --oracle-nulls 30 --md FILE`.
# Every mode first runs the generator's, the grader's and the oracle's own
# checks (test_v3.py, test_score.py, test_oracle.py, about 10 s); the
# default (CI) mode also the frame-error check (frames_check.py) and the
# quick form of the oracle comparison (`power.py --quick --check`: one
# run per class at 0.5 and 2x the visible noise, two effect-free runs per
# regime, its gates in power.py `ci_gates`; about 60 s on two cores).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
(cd "$here" && "${PYTHON:-python3}" -m unittest -q test_v3 test_score test_oracle)
# PERPEND_BIN set (CI: the binary `cargo xtask test` built): used as is.
if [ -z "${PERPEND_BIN:-}" ]; then
    (cd "$root" && cargo build --quiet -p perpend-cli --bin perpend)
    target="${CARGO_TARGET_DIR:-$root/target}"
    case "$target" in /*) ;; *) target="$root/$target" ;; esac
    PERPEND_BIN="$target/debug/perpend"
fi
if [ "${1:-}" = "--v3" ]; then
    shift
    exec "${PYTHON:-python3}" "$here/score.py" --v3 --perpend "$PERPEND_BIN" "$@"
fi
if [ "${1:-}" = "--power" ]; then
    shift
    exec "${PYTHON:-python3}" "$here/power.py" --perpend "$PERPEND_BIN" "$@"
fi
if [ "${1:-}" = "--full" ]; then
    exec "$PERPEND_BIN" bench diagnose --blind "$here" "$@"
fi
# The tracker-tilt estimate of `perpend frames` on gen.py's reversal runs
# (frames_check.py: 10 tilted + 10 tilt-free runs per regime, ~10 s).
"${PYTHON:-python3}" "$here/frames_check.py" "$PERPEND_BIN" --runs 10
# The diagnosis beside the oracle, quick form (power.py; issue 46).
"${PYTHON:-python3}" "$here/power.py" --perpend "$PERPEND_BIN" --quick --check
case " $* " in *" --check "*) exec "$PERPEND_BIN" bench diagnose --blind "$here" "$@" ;; esac
exec "$PERPEND_BIN" bench diagnose --blind "$here" --check "$@"

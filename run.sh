#!/usr/bin/env bash
# The README's two commands: `./run.sh serve` and `./run.sh test`. Each sets everything up first
# (scripts/setup.sh, idempotent) and then does its one job.
set -euo pipefail
cd "$(dirname "$0")"
bash scripts/setup.sh
case "${1:-}" in
    serve)
        shift
        # Until the HTTP service lands, the main job is the evaluation on a small set.
        exec .venv/bin/catalign evaluate --method fpfh --max-shapes 6 --views 1 "$@"
        ;;
    test)
        shift
        exec .venv/bin/python -m pytest "$@"
        ;;
    *)
        echo "usage: ./run.sh serve|test [extra arguments]" >&2
        exit 2
        ;;
esac

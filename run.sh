#!/usr/bin/env bash
# The README's two commands: `./run.sh serve` and `./run.sh test`. Each sets everything up first
# (scripts/setup.sh, idempotent) and then does its one job.
set -euo pipefail
cd "$(dirname "$0")"
case "${1:-}" in
    serve)
        shift
        bash scripts/setup.sh
        # The shipped model and default library (model_store/), HTTP on 8000, gRPC on 50051.
        exec .venv/bin/catalign serve "$@"
        ;;
    test)
        shift
        bash scripts/setup.sh --test
        exec .venv/bin/python -m pytest "$@"
        ;;
    *)
        echo "usage: ./run.sh serve|test [extra arguments]" >&2
        exit 2
        ;;
esac

"""Write the HTTP contract, ``openapi.yaml``, from the app; ``--check`` only compares.

The file is generated, never edited by hand: the SDK and reviewers read it, and a test fails
when it differs from what the app serves. Building the app loads nothing (no weights, no
library), so this runs in a second.

    python scripts/export_openapi.py            # rewrite openapi.yaml
    python scripts/export_openapi.py --check    # exit 1 if openapi.yaml is stale
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import yaml

from catalign.api.app import create_app
from catalign.api.settings import ServiceSettings

logger = logging.getLogger("export_openapi")

DEFAULT_PATH = Path(__file__).resolve().parents[1] / "openapi.yaml"


def render() -> str:
    """The app's OpenAPI document as YAML (keys in the app's order, so diffs stay readable)."""
    schema = create_app(ServiceSettings()).openapi()
    return yaml.safe_dump(schema, sort_keys=False, allow_unicode=True, width=100)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Write or check openapi.yaml.")
    parser.add_argument("--check", action="store_true", help="exit 1 if the file differs")
    parser.add_argument("--out", type=Path, default=DEFAULT_PATH, help="file to write or check")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    text = render()
    current = args.out.read_text() if args.out.is_file() else None
    if args.check:
        if current != text:
            logger.error("%s is stale; run: python scripts/export_openapi.py", args.out)
            return 1
        logger.info("%s is up to date", args.out)
        return 0
    args.out.write_text(text)
    logger.info("wrote %s", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

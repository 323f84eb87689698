"""The bad-input table's page: ``python -m tests.bench bad_input`` runs the table of
``tests/bad_input_table.py`` (the one ``tests/test_bad_input.py`` runs) and writes each case's
message."""

from __future__ import annotations

import argparse

from tests.bad_input_table import table_markdown
from tests.bench.report import RESULTS, publish_report


def main(argv: list[str] | None = None) -> int:
    """Run the table and write its page."""
    ap = argparse.ArgumentParser(prog="python -m tests.bench bad_input", description=__doc__)
    ap.add_argument("--out", default=str(RESULTS / "BAD_INPUT.md"), help="the page to write")
    return publish_report(table_markdown(), ap.parse_args(argv).out)

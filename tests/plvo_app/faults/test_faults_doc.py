"""docs/faults.md stays true: every row names a test that exists and looks the row up; every test file's rows exist."""

from __future__ import annotations

import re
from pathlib import Path

from faults_table import faults

REPO = Path(__file__).resolve().parents[3]


def test_every_row_names_an_existing_test_that_uses_it():
    rows = faults()
    assert len(rows) >= 15
    for row in rows.values():
        path, _, name = row.test.partition("::")
        source = (REPO / path).read_text()
        body = re.search(rf"^def {name}\(.*?(?=^def |\Z)", source, re.S | re.M)
        assert body, f"{row.id}: {row.test} not found"
        assert f'fault("{row.id}")' in body.group(0), f"{row.id}: {row.test} does not look its row up"


def test_every_fault_looked_up_is_in_the_table():
    rows = faults()
    used = set()
    for path in (REPO / "tests").rglob("test_*.py"):
        used |= set(re.findall(r'\bfault\("([a-z-]+)"\)', path.read_text()))
    assert used and used <= set(rows), used - set(rows)
    assert set(rows) <= used, set(rows) - used

"""scripts/results_table.py on the shipped cards: one row per policy, the default first; a one-line error without cards."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_one_row_per_shipped_policy_the_default_first():
    done = subprocess.run([sys.executable, "scripts/results_table.py"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    rows = done.stdout.splitlines()[2:]
    assert len(rows) == len(list((REPO / "models").glob("*.json")))
    assert "(default)" in rows[0] and all("(default)" not in row for row in rows[1:])
    assert all("`recipes/" in row and "(200000..200499, gym-pusht)" in row for row in rows)


def test_no_cards_is_a_one_line_error(tmp_path):
    done = subprocess.run(
        [sys.executable, "scripts/results_table.py", "--models-dir", str(tmp_path)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2 and done.stderr.strip() == f"error: no policy cards (*.json) in {tmp_path}"

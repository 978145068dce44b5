"""scripts/results_table.py on the real records: one row per recorded checkpoint, the shipped runs marked."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def test_table_of_the_real_records():
    done = subprocess.run([sys.executable, "scripts/results_table.py", "--env", "pusht"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    rows = done.stdout.splitlines()[2:]
    records = [p for p in (REPO / "records").iterdir() if (p / "last.json").is_file()]
    assert len(rows) == sum(1 + (p / "best.json").is_file() for p in records)  # final and best (fine-tuning keeps no best)
    shipped = {row.split(" | ")[0].lstrip("| "): row.rstrip(" |").rsplit(" | ", 1)[-1] for row in rows if " final " in row}
    assert shipped["flow-outcome16-stretch"] == "flow" and shipped["mse-sincos-skip-100k"] == "mse"
    assert shipped["flow-outcome16"] not in ("flow", "mse")  # the chooser it continues, shipped before
    assert shipped["flow-agentframe-padend-150k-noise0.3"] not in ("flow", "mse")  # the flow it fine-tunes, shipped before


def test_no_records_is_a_one_line_error(tmp_path):
    done = subprocess.run([sys.executable, "scripts/results_table.py", "--records-dir", str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stderr.strip() == f"error: no run records (*/last.json) in {tmp_path}"

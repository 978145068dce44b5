"""scripts/results_table.py on the real records: one row per recorded checkpoint, the shipped runs marked."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CHOOSER = REPO / "records" / "flow-outcome16-stretch" / "last.json"


def _final_marks(*args: str) -> dict[str, str]:
    """{record name: its final row's "shipped as" cell} of the pusht table."""
    done = subprocess.run([sys.executable, "scripts/results_table.py", "--env", "pusht", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    rows = done.stdout.splitlines()[2:]
    records = [p for p in (REPO / "records").iterdir() if (p / "last.json").is_file()]
    assert len(rows) == sum(1 + (p / "best.json").is_file() for p in records)  # final and best (fine-tuning keeps no best)
    return {row.split(" | ")[0].lstrip("| "): row.split(" | ")[-1].rstrip(" |") for row in rows if " final " in row}


def test_table_of_the_real_records(tmp_path):
    shipped = _final_marks()
    # the rows marked are those of the records that the cards in models/ name, and no other (a card without `run`, as
    # a student copied in by hand, marks none)
    named = {Path(json.loads(card.read_text()).get("run") or "").name: card.stem for card in (REPO / "models").glob("*.json")}
    assert {name: mark for name, mark in shipped.items() if mark} == {name: stem for name, stem in named.items() if name in shipped}
    assert shipped["mse-sincos-skip-100k"] == "mse"
    # a models folder whose flow is the chooser record: its row is marked, not the runs it continues
    (tmp_path / "flow.json").write_text(json.dumps({**json.loads(CHOOSER.read_text()), "run": "records/flow-outcome16-stretch"}))
    shutil.copyfile(REPO / "models" / "mse.json", tmp_path / "mse.json")
    shipped = _final_marks("--models-dir", str(tmp_path))
    assert shipped["flow-outcome16-stretch"] == "flow" and shipped["mse-sincos-skip-100k"] == "mse"
    assert shipped["flow-outcome16"] == ""  # the chooser it continues, shipped before
    assert shipped["flow-agentframe-padend-150k-noise0.3"] == ""  # the flow it fine-tunes, shipped before


def test_no_records_is_a_one_line_error(tmp_path):
    done = subprocess.run([sys.executable, "scripts/results_table.py", "--records-dir", str(tmp_path)], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stderr.strip() == f"error: no run records (*/last.json) in {tmp_path}"

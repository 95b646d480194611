"""The benchmark scripts that call obsjax's internals still run: a change of an internal signature (e.g. the
balancing that ``place`` passes to its compiled core) otherwise surfaces only when a benchmark is re-run.
Each runs on the smallest problem, writing its table to a temporary folder (``OBSJAX_BENCH_RESULTS``), never
to ``benchmarks/results/``."""

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

pytestmark = pytest.mark.extended


@pytest.mark.parametrize(
    "script, args, table",
    [
        ("f_placement.py", ["--sets", "3", "--ns", "4"], "f_placement.md"),
        ("f_placement_estimate.py", ["--sets", "3", "--ns", "4", "--sets-20", "3"], "f_placement_estimate.md"),
    ],
)
def test_placement_benchmarks_run_on_a_small_problem(tmp_path, script, args, table):
    env = dict(os.environ, OBSJAX_BENCH_RESULTS=str(tmp_path))
    out = subprocess.run(
        [sys.executable, os.path.join(ROOT, "benchmarks", script), *args],
        cwd=os.path.join(ROOT, "benchmarks"), env=env, capture_output=True, text=True, timeout=600,
    )
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-4000:]
    text = (tmp_path / table).read_text()
    # the n = 4 row is there, with obsjax's placement error measured (a number, not a failure marker)
    row = next(line for line in text.splitlines() if line.startswith("| 4 |"))
    assert "nan" not in row.lower(), row

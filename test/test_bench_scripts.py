"""The benchmark scripts still run against the code they measure: each on one small
built-in subject and a few frames (their numbers are the benchmarks' business, in
bench/README.md; this catches a script the code moved under, as the growth window once
did to bench_skeleton.py)."""
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _table_rows(script: str, *args) -> list:
    """The Markdown rows the script prints for the arm, as lists of cells."""
    done = subprocess.run([sys.executable, str(REPO / 'bench' / script), *args], capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return [[cell.strip() for cell in line.strip().strip('|').split('|')]
            for line in done.stdout.splitlines() if line.startswith('| arm |')]


def test_bench_skeleton_scores_steps_2_and_3():
    rows = _table_rows('bench_skeleton.py', '--frames', '24', '--subjects', 'arm', '--no-dem-bones', '--no-surface')
    assert [row[2] for row in rows] == ['step 2 (structure)', 'step 3 (Alg. 2)', '(registration, steps 0-1)']
    for row in rows[:2]:
        found, mean_error, recall = int(row[3]), float(row[4]), float(row[6])
        # the arm's two true joints are found, well within the arm's length
        assert found >= 2 and recall == 1.0 and mean_error < 0.1, row


def test_bench_registration_runs_the_registration_and_the_skeleton_tracker():
    rows = _table_rows('bench_registration.py', '--sequences', 'arm', '--frames', '24',
                       '--methods', 'ours,tracker,static')
    by_method = {row[2]: row for row in rows}
    assert set(by_method) == {'ours', 'tracker', 'static'}, rows
    mean = {method: float(row[3]) for method, row in by_method.items()}
    after_window = {method: float(row[7]) for method, row in by_method.items()}
    # both follow the arm: far nearer the truth than the rest pose held still
    assert mean['ours'] < 0.5 * mean['static'] and mean['tracker'] < 0.5 * mean['static'], mean
    assert after_window['tracker'] < 0.5 * after_window['static'], after_window

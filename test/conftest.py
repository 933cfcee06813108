"""Shared fixtures: the bundled sample bag, its `skel-extract run` output, small simulated sequences."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from skel_extract_ros.sim import NoiseModel, generate_sequence

REPO_ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = REPO_ROOT / 'bags' / 'sample_wave'


@pytest.fixture(scope='session')
def sample_bag() -> Path:
    assert (SAMPLE_BAG / 'metadata.yaml').is_file(), 'the sample bag must be committed in bags/'
    return SAMPLE_BAG


CLI = shutil.which('skel-extract', path=str(Path(sys.executable).parent)) or 'skel-extract'


def run_cli(*args, timeout=900):
    return subprocess.run([CLI, *map(str, args)], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope='session')
def sample_run(sample_bag, tmp_path_factory):
    """(completed process, output dir) of `skel-extract run` on the sample bag (run once)."""
    out = tmp_path_factory.mktemp('sample_run') / 'out'
    return run_cli('run', sample_bag, '--out', out), out


@pytest.fixture(scope='session')
def human_clean():
    """20 noise-free frames of the full body."""
    return generate_sequence('human', 20, noise=NoiseModel.none(), seed=3, progress=False)


@pytest.fixture(scope='session')
def human_noisy():
    return generate_sequence('human', 20, seed=3, progress=False)

"""Shared fixtures: the bundled sample bag and small simulated sequences."""
from pathlib import Path

import pytest

from skel_extract_ros.sim import NoiseModel, generate_sequence

REPO_ROOT = Path(__file__).resolve().parents[1]
SAMPLE_BAG = REPO_ROOT / 'bags' / 'sample_human'


@pytest.fixture(scope='session')
def sample_bag() -> Path:
    assert (SAMPLE_BAG / 'metadata.yaml').is_file(), 'the sample bag must be committed in bags/'
    return SAMPLE_BAG


@pytest.fixture(scope='session')
def human_clean():
    """20 noise-free frames of the full body."""
    return generate_sequence('human', 20, noise=NoiseModel.none(), seed=3, progress=False)


@pytest.fixture(scope='session')
def human_noisy():
    return generate_sequence('human', 20, seed=3, progress=False)

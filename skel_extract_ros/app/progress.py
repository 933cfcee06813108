"""Progress bars for long work: tqdm on stderr, refreshed rarely when not on a terminal so
CI logs and pipes get a handful of lines rather than one per frame."""
import sys

from tqdm import tqdm


def progress_bar(**kwargs) -> tqdm:
    interactive = sys.stderr.isatty()
    kwargs.setdefault('mininterval', 0.1 if interactive else 5.0)
    kwargs.setdefault('leave', interactive)
    return tqdm(file=sys.stderr, **kwargs)

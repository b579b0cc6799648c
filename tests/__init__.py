"""ilt's tests, one folder per package of ilt/ (tests/transport/ tests ilt/transport/ ...)."""

from pathlib import Path

#: the repository's root (configs/, benchmarks/, scripts/)
ROOT = Path(__file__).resolve().parent.parent

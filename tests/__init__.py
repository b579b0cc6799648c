"""ilt's tests, one folder per package of ilt/ (tests/transport/ tests ilt/transport/ ...)."""

from pathlib import Path

#: the repository's root (configs/, benchmarks/, scripts/)
ROOT = Path(__file__).resolve().parent.parent


def load_benchmark(name: str):
    """The module ``benchmarks/NAME.py`` (benchmarks are scripts, not a package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module

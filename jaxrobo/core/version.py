"""The package version: one home, read by ``pyproject.toml`` (``[tool.setuptools.dynamic]``), ``jaxrobo.__version__``,
checkpoints and sweep state; and :func:`installed`, the version of a dependency (for the version guards of the
modules that reach into one's private code)."""
import functools
import importlib.metadata

__version__ = "0.1.0"


@functools.lru_cache(maxsize=None)
def installed(distribution: str) -> str | None:
    """The installed version string of ``distribution`` (a pip name), or None if its metadata cannot be found."""
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None

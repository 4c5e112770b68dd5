"""The package version: one home, read by ``pyproject.toml`` (``[tool.setuptools.dynamic]``), ``jaxrobo.__version__``,
checkpoints and sweep state; :func:`installed`, the version of a dependency; :func:`outside`, the version guards'
check, and :func:`warn_once`, their warning (for the modules that reach into one's private code); and
:func:`source_hash`, the identity of the code itself."""
import functools
import importlib.metadata
import os
import re
import warnings

__version__ = "0.1.0"


def outside(package: str, version: str | None, written_for: tuple[tuple[int, int], tuple[int, int]],
            what: str = "it") -> str | None:
    """Why ``version`` of ``package`` is outside ``written_for`` (``(low, high)`` as ``(major, minor)``, high
    excluded), the range ``what`` was written for (a sentence), or None when it is inside: the check of every
    module that reaches into a dependency's private code."""
    if version is None:
        return f"the {package} package metadata was not found, so its version cannot be checked"
    match = re.match(r"(\d+)\.(\d+)", version)
    low, high = written_for
    if match is None or not low <= (int(match[1]), int(match[2])) < high:
        return (f"{package} {version} is outside the versions {what} was written for "
                f"(>= {low[0]}.{low[1]}, < {high[0]}.{high[1]})")
    return None


def warn_once(seen: set[str], message: str, stacklevel: int = 3) -> None:
    """``message`` as a :class:`RuntimeWarning` the first time a module warns it (``seen``: that module's messages
    warned so far, which a test may empty), whatever the warnings filters say of repeats; ``stacklevel`` counted from
    here, as :func:`warnings.warn` counts it: a version guard's "runs as it is" said once per process."""
    if message not in seen:
        seen.add(message)
        warnings.warn(message, RuntimeWarning, stacklevel=stacklevel)


@functools.lru_cache(maxsize=None)
def installed(distribution: str) -> str | None:
    """The installed version string of ``distribution`` (a pip name), or None if its metadata cannot be found."""
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


#: Checkpoints of runs and sweeps record :func:`source_hash`: resuming under other code is refused (a carry from
#: other code would not continue the same run bit for bit); kept traces are keyed on it (jaxrobo.speed.reuse).
_SOURCE_DIRS = ("jaxrobo", "envs", "agents")
_SOURCE_SUFFIXES = (".py", ".xml")


def source_hash() -> str:
    """SHA-256 over the code that shapes a run (``jaxrobo``, ``envs``, ``agents``: Python and MJCF files)."""
    import hashlib

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    h = hashlib.sha256()
    for top in _SOURCE_DIRS:
        for dirpath, dirnames, files in os.walk(os.path.join(root, top)):
            dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
            for name in sorted(f for f in files if f.endswith(_SOURCE_SUFFIXES)):
                path = os.path.join(dirpath, name)
                h.update(os.path.relpath(path, root).encode() + b"\0")
                with open(path, "rb") as f:
                    h.update(f.read() + b"\0")
    return h.hexdigest()

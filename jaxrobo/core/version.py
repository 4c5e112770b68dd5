"""The package version: one home, read by ``pyproject.toml`` (``[tool.setuptools.dynamic]``), ``jaxrobo.__version__``,
checkpoints and sweep state."""
__version__ = "0.1.0"

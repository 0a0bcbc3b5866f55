"""The version of the package (pyproject.toml reads it here; `deepcharuco --version` prints it)."""

__version__ = "0.1.0"

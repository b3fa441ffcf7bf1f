"""The package's version (also ``tmrl.__version__``; pyproject.toml says the same)."""

__version__ = "0.1.0"

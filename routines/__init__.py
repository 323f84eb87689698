"""slidecal.routines."""

#: The package's version, read by the build (pyproject.toml) and written into every export
__version__ = "0.1.0"

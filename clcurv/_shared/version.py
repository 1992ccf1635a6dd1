"""The version of clcurv: read by clcurv/__init__.py (``clcurv.__version__``), by the tiled
run's resume key (:func:`clcurv.tiles.workspace.code_key`) and by the build
(pyproject.toml: ``[tool.setuptools.dynamic]``), so that it is written in this one place."""

__version__ = "0.1.0"

"""photopft core: the science, free of Qt and of drivers."""

__version__ = "0.1.0"

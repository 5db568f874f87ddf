"""Generators for synthetic velocity models and small example data sets."""
from .generators import constant, gaussian_anomaly, layered, write_example_files

__all__ = ["constant", "gaussian_anomaly", "layered", "write_example_files"]

"""Silva's science core: features, the forest cascade, metrics, LiDAR I/O, synthetic scenes.

Everything here works on NumPy arrays and files; nothing imports Dask or reads YAML.
"""

__version__ = "0.1.0"

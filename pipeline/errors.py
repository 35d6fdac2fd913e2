"""One exception hierarchy for everything Silva refuses to do.

Every message is one line that says what is wrong and how to fix it; the command line prints
it as it is and exits with code 1. Subclasses also inherit the matching built-in, so callers
can catch either.
"""


class SilvaError(Exception):
    """Base of every error Silva raises on purpose."""


class InputError(SilvaError, ValueError):
    """Input data that cannot be used: empty or corrupt tiles, NaN coordinates, wrong shapes."""


class MissingFileError(SilvaError, FileNotFoundError):
    """A file or directory that should exist does not."""


class ConfigError(SilvaError, ValueError):
    """A configuration value or key that is not valid."""


class ModelError(SilvaError, ValueError):
    """A saved model that cannot be loaded or does not fit the configuration."""


class StoreError(SilvaError, RuntimeError):
    """A zarr store that is missing, incomplete or written by another configuration."""


class ChunkError(SilvaError, RuntimeError):
    """A chunk task that failed; the message names the chunk, its tiles and how to rerun it."""

"""DELTA: disentangled hybrid (mesh + NeRF) avatars from monocular video."""

__version__ = "0.1.0"


class DeltaError(Exception):
    """An error the user can act on: the message names the file, key or frame at fault."""

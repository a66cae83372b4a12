"""Transitional: the module moved to ``modules`` (split into modules in the next commit)."""
from navcrafter.models.geometry.vggt import modules as _moved

globals().update({k: v for k, v in vars(_moved).items() if not k.startswith("__")})

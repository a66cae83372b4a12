"""Transitional: the module moved to ``processing`` (split into modules in the next commit)."""
from navcrafter.models.geometry.moge import processing as _moved

globals().update({k: v for k, v in vars(_moved).items() if not k.startswith("__")})

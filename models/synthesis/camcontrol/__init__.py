"""Transitional: the module moved to ``model`` (split into modules in the next commit)."""
from navcrafter.models.synthesis.camcontrol import model as _moved

globals().update({k: v for k, v in vars(_moved).items() if not k.startswith("__")})

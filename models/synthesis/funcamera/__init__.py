"""Transitional: the module moved to ``weights`` (split into modules in the next commit)."""
from navcrafter.models.synthesis.funcamera import weights as _moved

globals().update({k: v for k, v in vars(_moved).items() if not k.startswith("__")})

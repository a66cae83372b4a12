"""The base of every model package's settings (its ``config.py``): frozen pydantic sections, unknown keys refused.

schemas/config.py composes the sections into the run configuration; models never see that composition.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

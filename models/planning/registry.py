"""Every planner behind ``plan.strategy`` (the plan step's lookup): the paper's collision-aware planner and the
global ViewCrafter-utility baseline (``planners.py``), ViewCrafter's NBV from the current pose (``nbv.py``) and the
safe explorer (``explore.py``)."""

from __future__ import annotations

from navcrafter.models.planning.explore import ExplorerPlanner
from navcrafter.models.planning.nbv import ViewCrafterNBVPlanner
from navcrafter.models.planning.planners import PLANNERS as _BASE

PLANNERS = {**_BASE, ViewCrafterNBVPlanner.name: ViewCrafterNBVPlanner, ExplorerPlanner.name: ExplorerPlanner}

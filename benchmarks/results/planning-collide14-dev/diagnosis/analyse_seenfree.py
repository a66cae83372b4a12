"""Run collide13's analyse.py with the detector's explore_ball_seen_free on (collide14):
python analyse_seenfree.py STORE BASE [KEY=VALUE ...]"""
import runpy
import sys
from pathlib import Path

from navcrafter.models.planning import explore as ex

init = ex.ExplorerDetector.__init__


def patched(self, *args, **kwargs):
    kwargs["ball_seen_free"] = True
    init(self, *args, **kwargs)


ex.ExplorerDetector.__init__ = patched
here = Path(__file__).resolve().parents[2] / "planning-collide13-dev" / "diagnosis" / "analyse.py"
sys.path.insert(0, str(here.parent))
sys.argv = [str(here), *sys.argv[1:]]
runpy.run_path(str(here), run_name="__main__")

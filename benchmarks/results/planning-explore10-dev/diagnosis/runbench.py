"""Run benchmarks/planning.py from a chosen source tree (python runbench.py TREE ARGS...): the venv's editable
install is pointed at TREE; with KEEP_STORES=DIR the benchmark's stores are kept under DIR for diagnosis."""
import contextlib
import os
import runpy
import sys
import tempfile

import __editable___navcrafter_0_1_0_finder as f  # the venv's editable install (setuptools)

tree = sys.argv[1]

for k in list(f.MAPPING):
    f.MAPPING[k] = os.path.join(tree, k.split(".")[1])
keep = os.environ.get("KEEP_STORES")
if keep:
    def _td(prefix=None, **kw):
        return contextlib.nullcontext(tempfile.mkdtemp(prefix=prefix, dir=keep))
    tempfile.TemporaryDirectory = _td
sys.argv = [os.path.join(tree, "benchmarks/planning.py")] + sys.argv[2:]
sys.path.insert(0, os.path.join(tree, "benchmarks"))
runpy.run_path(sys.argv[0], run_name="__main__")

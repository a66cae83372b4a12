"""``python -m navcrafter.flows.cli``: the ``navcrafter`` command without the console script (tests run it so)."""

from navcrafter.flows.cli import main

main()

"""Simulation mode: procedural ground-truth scenes (and scanned worlds) standing in for learned models."""

LABEL = ("SIMULATION MODE: rendered from procedurally generated ground truth, "
         "not produced by learned models")

GROUNDTRUTH_DIR = ".groundtruth"  # beside demo photos: <folder>/.groundtruth/<photo stem>/scene.json


def simulation_label(scene: dict | None = None) -> str:
    """The SIMULATION label of a run on ``scene`` (the ``scene`` spec of its ground-truth record, ``scene.json`` /
    ingest's ``simulation_truth``): a scanned world's (``worlds.LABEL``) for a scan, else ``LABEL`` (generated
    scenes; also when the scene is not known). The one place that decides which label a simulated scene gets."""
    # deferred: the package's __init__ stays a leaf that its sub-packages (worlds among them) import constants from
    from navcrafter.models.simulation.worlds import LABEL as SCAN_LABEL
    from navcrafter.models.simulation.worlds import SCAN_KIND

    return SCAN_LABEL if isinstance(scene, dict) and scene.get("kind") == SCAN_KIND else LABEL

"""Simulation mode: procedural ground-truth scenes standing in for learned models."""

LABEL = ("SIMULATION MODE: rendered from procedurally generated ground truth, "
         "not produced by learned models")

GROUNDTRUTH_DIR = ".groundtruth"  # beside demo photos: <folder>/.groundtruth/<photo stem>/scene.json

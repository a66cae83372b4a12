"""The tasks of ``navcrafter train-camera`` (camera-control training of the Wan2.1 video DiT), plain functions
the flow calls: ``clips`` (plan the training clips, precompute the clip store, read it back), ``train`` (the
run folder, training, validation, export) and ``worker`` (one DDP process). Configuration and stored layout:
``schemas/training.py``."""

"""Exported model directories: their layout and labels, the ``onnx`` backend's roles built from one
(``modeldir``), the exporters of every role (``exporters``) and ``navcrafter models pull`` (``hub``).

The top of the models layer: it builds on every role package (synthesis, geometry, refiner) and models/runtime.
"""

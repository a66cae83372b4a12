"""The Refiner role: a Difix-architecture single-step diffusion refiner (``difix``) and its onnxruntime runner
(``onnx_refiner``)."""

"""Novel-view video synthesis: the camera-controlled Wan2.1 DiT and what runs around it.

* ``camcontrol`` — the camera-controlled DiT (``CameraControlledWan``): diffusers' ``WanTransformer3DModel``
  plus a Plücker camera adapter (dual-branch injection), a LoRA control branch on the self-attention
  Q/K/V, reference-frame attention and point-cloud render conditioning; weights I/O and ONNX export.

Submodules are imported on demand (``from navcrafter.models.synthesis.camcontrol import ...``) so that
importing this package pulls in neither torch nor diffusers.
"""

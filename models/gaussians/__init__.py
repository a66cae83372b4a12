"""3D Gaussian Splatting: a gsplat-compatible differentiable rasterizer (pure PyTorch on CPU), the Gaussian
model container and its initialisation from a point cloud, the standard 3DGS PLY format, and DropGaussian.

Conventions are navcrafter's (``models/camera/cameras.py``): OpenCV cameras, pixel centres at ``j + 0.5``, z-depth,
quaternions ``(w, x, y, z)``. Renderer inputs are world-to-camera ``viewmats`` (the inverse of navcrafter's
camera-to-world poses), as gsplat expects.
"""

from navcrafter.models.gaussians.model import GaussianModel
from navcrafter.models.gaussians.rasterize import rasterization

__all__ = ["GaussianModel", "rasterization"]

"""Differentiable Gaussian rasterization (see rasterize.py)."""
from .camera import Camera
from .projection import EPS2D, Projected, frustum_cull, project_gaussians
from .rasterize import rasterize
from .types import RenderOutput

__all__ = ["EPS2D", "Camera", "Projected", "RenderOutput", "frustum_cull", "project_gaussians", "rasterize"]

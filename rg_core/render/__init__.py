"""Differentiable Gaussian rasterization (see rasterize.py)."""
from .camera import Camera
from .projection import EPS2D, Projected, project_gaussians
from .rasterize import rasterize
from .types import RenderOutput

__all__ = ["EPS2D", "Camera", "Projected", "RenderOutput", "project_gaussians", "rasterize"]

"""Differentiable Gaussian rasterization (see rasterize.py)."""
from .camera import Camera
from .projection import Projected, project_gaussians
from .rasterize import RenderOutput, rasterize

__all__ = ["Camera", "Projected", "RenderOutput", "project_gaussians", "rasterize"]

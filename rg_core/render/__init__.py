"""Differentiable Gaussian rasterization (see rasterize.py)."""
from .camera import Camera
from .projection import Projected, project_gaussians
from .rasterize import rasterize
from .types import RenderOutput

__all__ = ["Camera", "Projected", "RenderOutput", "project_gaussians", "rasterize"]

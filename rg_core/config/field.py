"""Section of the scale-hierarchical feature field (rg_core/field)."""
from __future__ import annotations

from typing import Annotated

from annotated_types import Interval

from .schema import section


@section
class FieldConfig:
    """Scale-hierarchical feature field: latent per Gaussian, language and instance mappers."""

    latent_dim: int = 32
    """Latent feature f per Gaussian, rendered with the same alpha blending as colour."""
    language_dim: int = 64
    """Output of F_l(s, f): the PCA space of the mask embeddings."""
    instance_dim: int = 16
    """Output of F_g(s, f): unit-normalised instance feature."""
    hidden: int = 64
    """Width of the two hidden layers of each mapper."""
    scale_frequencies: int = 4
    """Sin/cos frequencies of the normalised scale fed to the mappers (sharp steps in scale)."""
    scale_knots: int = 33
    """Knots of the monotone quantile transform of mask scales (fitted on supervision scales)."""
    rays_per_step: int = 256
    """Pixels sampled from the rendered view per training step."""
    mask_ray_fraction: float = 0.75
    """Share of rays drawn inside masks, equally per mask (small objects get rays); rest uniform."""
    scales_per_step: int = 4
    """Scales at which the contrastive loss is evaluated per step."""
    huber_delta: float = 0.1
    """Huber delta of the language loss (PCA-space units)."""
    margin: float = 1.0
    """Contrastive margin lambda: pairs not sharing a group are pushed at least this far apart."""
    lambda_language: float = 1.0
    """Weight of L_lang."""
    lambda_instance: float = 0.1
    """Weight of L_in."""
    lambda_consistency: float = 0.1
    """Pull each sampled pixel's dominant Gaussian latent to the pixel's blended latent (grouping
    applies the mappers per Gaussian; training sees blends)."""
    lr_latents: float = 0.01
    """Adam learning rate of the per-Gaussian latents (only rows seen by the step move)."""
    lr_mappers: float = 0.002
    """Adam learning rate of the two mappers."""
    init_std: float = 0.1
    """Std dev of the random latents of a map that had none."""
    init_neighbours: int = 3
    """New Gaussians start from the mean latent of this many nearest existing Gaussians."""
    window: int = 8
    """Recent supervised keyframes trained together ..."""
    revisit: float = 0.2
    """... and the probability of a step on an older one instead (0: strictly the window)."""
    train_width: int = 160
    """Training renders at most this wide (cheaper steps); masks are resampled to it."""
    seconds: float = 80.0
    """Ceiling of `train()` without a budget: it stops earlier once converged (converge_tol)."""
    steps: Annotated[int, Interval(ge=0)] = 0
    """> 0: train exactly this many steps instead, no stop test (runs comparable by count, not CPU speed)."""
    converge_tol: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.005
    """Stop once the best held-out accuracy (field/converge.py) gained less than this over
    converge_window steps (0: always the whole budget). Counted in steps, not seconds."""
    converge_window: Annotated[int, Interval(ge=1)] = 50
    converge_min_steps: Annotated[int, Interval(ge=0)] = 50
    """The stop test's floor (steps since the supervision last changed)."""
    check_every: Annotated[int, Interval(ge=1)] = 20
    """Steps between held-out measurements."""
    holdout: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.1
    """Share of each supervised view's pixels never trained on; the stop test measures there."""
    holdout_views: Annotated[int, Interval(ge=1)] = 4
    """Supervised views (spread over the map) the stop test measures in."""
    seed: int = 0
    """Random seed of latents, mappers and ray sampling."""

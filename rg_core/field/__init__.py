"""Scale-hierarchical feature Gaussian field: a latent per Gaussian, F_l(s, f) and F_g(s, f)."""
from .field import FeatureField, FieldRender
from .losses import instance_loss, language_loss, language_targets, shares_group
from .mappers import ScaleMLP
from .scale import QuantileScale

__all__ = ["FeatureField", "FieldRender", "QuantileScale", "ScaleMLP", "instance_loss", "language_loss",
           "language_targets", "shares_group"]

"""Types every perception backend shares: the error a backend raises when it cannot load, and a
2D mask with its confidence and level."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Mask:
    mask: np.ndarray   # [H, W] bool
    score: float       # confidence in [0, 1]
    level: int         # 0 part, 1 object, 2 group / support surface (SAM's three levels)


class BackendError(RuntimeError):
    """A model backend cannot load: the message names the missing file or package."""

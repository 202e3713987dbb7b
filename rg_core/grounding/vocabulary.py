"""Object names a reasoner may pick from: the caller's (scene) names, configured extras, and the
built-in household names that the map's own mask embeddings support."""
from __future__ import annotations

import torch

HOUSEHOLD = (
    "apple", "banana", "lemon", "orange", "peach", "pear", "plum", "cup", "coffee mug", "bowl", "plate",
    "spoon", "fork", "knife", "scissors", "stapler", "marker", "pen", "pencil", "hammer", "screwdriver",
    "clamp", "wrench", "pliers", "glue stick", "correction fluid", "remote control", "shampoo",
    "conditioner", "soap", "toothpaste", "toothbrush", "rubber duck", "teddy bear", "lego brick",
    "wooden block", "cube", "ball", "toy box", "box", "bottle", "water bottle", "wine glass", "can",
    "jar", "pitcher", "kettle", "teapot", "pan", "pot", "sponge", "towel", "book", "notebook",
    "laptop", "keyboard", "computer mouse", "phone", "headphones", "camera", "clock", "lamp", "vase",
    "plant", "chair", "table", "shoe", "hat", "bag", "backpack", "wallet", "keys", "glasses",
    "tape", "battery", "flashlight", "cereal box", "cracker box", "sugar box", "mustard bottle",
    "tomato soup can", "tuna fish can", "pudding box", "gelatin box", "potted meat can", "bleach cleanser",
    "drill", "wood block", "foam brick", "extra large clamp", "large marker", "mug",
)


def supported_names(mask_embeddings: torch.Tensor, names: list[str], text_encoder) -> list[str]:
    """Names that are the nearest name of at least one mask embedding [M, D] (unit rows)."""
    if not len(mask_embeddings) or not names:
        return []
    t = torch.nn.functional.normalize(text_encoder(list(names)).float(), dim=-1)
    nearest = (torch.nn.functional.normalize(mask_embeddings.float(), dim=-1) @ t.T).argmax(-1)
    return [names[i] for i in sorted(set(nearest.tolist()))]


def build_vocabulary(scene_names, extra, mask_embeddings, text_encoder, use_support: bool = True,
                     synonym_similarity: float = 0.8) -> list[str]:
    """Scene names and configured extras always; household names when some mask supports them."""
    out: list[str] = []
    for n in list(scene_names) + list(extra):
        n = str(n).strip()
        if n and n not in out:
            out.append(n)
    if use_support:
        extra = [n for n in supported_names(mask_embeddings, list(HOUSEHOLD), text_encoder) if n not in out]
        if extra and out:
            # A near-synonym of a name already offered ("screwdriver" beside "phillips screwdriver")
            # is not another object: it only splits the reasoner's vote (+2 of 84 implicit queries
            # right on four synthetic scenes without them).
            sims = torch.nn.functional.normalize(text_encoder(extra).float(), dim=-1) @ \
                torch.nn.functional.normalize(text_encoder(out).float(), dim=-1).T
            extra = [n for n, s in zip(extra, sims.max(1).values.tolist()) if s < synonym_similarity]
        out += extra
    return out


_NOT_A_NAME = {"something", "thing", "things", "anything", "for", "to", "with", "that", "which", "what", "where",
               "used", "use", "can", "could", "i", "me", "my", "you", "want", "need", "would", "should", "from",
               "of", "in", "on", "is", "are", "hold", "holds", "make", "made"}


def looks_like_name(query: str) -> bool:
    """A short noun phrase ("orange", "the red mug") rather than a description: such a query is
    offered to the reasoner as a candidate name of its own, so an explicit query for an object the
    vocabulary lacks still passes straight through (the map then says whether anything matches)."""
    words = [w for w in query.lower().replace(",", " ").split() if w not in ("a", "an", "the", "some")]
    return 0 < len(words) <= 3 and not any(w in _NOT_A_NAME for w in words)

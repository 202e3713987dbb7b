"""The texts a query embeds: the Grounder's bounded cache of unit text embeddings, and the texts a
map stores so that a new process answers a query naming one of them without loading the text model.
"""
from __future__ import annotations

import torch

from .relevancy import CANONICAL
from .vocabulary import HOUSEHOLD

TEXT_CACHE_SIZE = 4096   # query and name embeddings kept per Grounder (1.5 KB each)


def encode_kept(encoder, kept: dict[str, torch.Tensor], texts: list[str]) -> torch.Tensor:
    """[n] strings -> [n, D] unit rows, each text embedded by `encoder` once while `kept` holds it
    (canonical phrases and names repeat); past TEXT_CACHE_SIZE texts the oldest go."""
    todo = [t for t in dict.fromkeys(texts) if t not in kept]
    if todo:
        for t, e in zip(todo, encoder(todo)):
            kept[t] = torch.nn.functional.normalize(e.float(), dim=-1)
    out = torch.stack([kept[t] for t in texts]) if texts else torch.zeros(0, 1)
    while len(kept) > TEXT_CACHE_SIZE:   # hours of distinct queries: the oldest go
        kept.pop(next(iter(kept)))
    return out


def store_texts(g) -> int:
    """Embed the texts a query on the Grounder's map needs besides the query itself (household,
    scene and configured names, their reasoner prompt form, the reasoner's background names, the
    canonical phrases) with MiniLM and keep them in the map's supervision (save_map stores them).
    -> count."""
    from ..perception.embed import MiniLMText
    from ..perception.reasoning.open_set import background_names
    from ..perception.reasoning.text import NAME_TEMPLATE

    sset = g.mapper.supervision
    if sset is None:
        raise ValueError("store_texts: the map has no supervision yet")
    names = list(dict.fromkeys(list(g.scene_names) + list(g.gcfg.vocabulary) + list(HOUSEHOLD)
                               + list(g.cfg.reason.extra_vocabulary)))
    texts = list(dict.fromkeys(names + [NAME_TEMPLATE.format(n) for n in names + list(background_names())]
                               + list(CANONICAL)))
    enc = g._text if isinstance(g._text, MiniLMText) else MiniLMText()
    sset.text_embeddings = dict(zip(texts, enc(texts)))
    return len(texts)

"""Name knowledge at run time: "name: gloss (a kind of hypernyms)" texts from the committed
WordNet extract rg_core/perception/data/name_knowledge.json (built by scripts/knowledge_build.py).

Used on both sides of the offline language stack (issue 15): the text reasoner compares a query
with each candidate name's knowledge text as well as with the name, and ConSE embeds ImageNet
classes by their knowledge texts (so "orange" and "lemon" sit near "citrus fruit").
A name the file lacks is composed from its longest known tail ("striped mug" -> "mug"'s gloss with
the modifier) or, failing that, stands as itself: any vocabulary works, the known ones better.
"""
from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path

from .base import BackendError

DEFAULT_PATH = Path(__file__).parent / "data" / "name_knowledge.json"
_ENTRY_KEYS = {"synset", "lemma", "gloss", "synonyms", "hypernyms"}


class KnowledgeError(BackendError):
    """The name-knowledge file is missing or unusable; the message names the file and the fault."""


def entry_text(name: str, e: dict, hypernyms: int = 2) -> str:
    """One knowledge text: 'orange cup: a orange cup, a small open container ... (a kind of
    crockery, tableware)'. The modifier stays in front of the head's gloss."""
    if not e.get("gloss"):
        return name
    head = f"{e['modifier']} {e['lemma']}, " if e.get("modifier") else ""
    syn = [s for s in e.get("synonyms", []) if s.lower() != name.lower()]
    extra = ([f"also {', '.join(syn[:2])}"] if syn else []) + (
        [f"a kind of {', '.join(e['hypernyms'][:hypernyms])}"] if e.get("hypernyms") and hypernyms else [])
    return f"{name}: {head}{e['gloss']}" + (f" ({'; '.join(extra)})" if extra else "")


class Knowledge:
    def __init__(self, data: dict, source: str = "<dict>"):
        if not isinstance(data, dict) or not isinstance(data.get("names"), dict) or \
                not isinstance(data.get("imagenet"), list):
            raise KnowledgeError(f"name knowledge {source}: expected an object with 'names' (object) and "
                                 f"'imagenet' (list), got keys {sorted(data) if isinstance(data, dict) else type(data).__name__}")
        for name, e in data["names"].items():
            if not isinstance(e, dict) or not _ENTRY_KEYS <= set(e):
                raise KnowledgeError(f"name knowledge {source}: entry {name!r} lacks {sorted(_ENTRY_KEYS - set(e or {}))}")
        if len(data["imagenet"]) != 1000 or not all(isinstance(e, dict) and "name" in e and _ENTRY_KEYS <= set(e)
                                                    for e in data["imagenet"]):
            raise KnowledgeError(f"name knowledge {source}: 'imagenet' must hold 1000 entries with name, "
                                 f"{sorted(_ENTRY_KEYS)}; got {len(data['imagenet'])}")
        self.names: dict[str, dict] = {k.lower(): v for k, v in data["names"].items()}
        self.imagenet: list[dict] = data["imagenet"]
        self.source = source

    def entry(self, name: str) -> dict | None:
        """The stored entry, or one composed from the longest known tail of the name."""
        key = " ".join(name.lower().split())
        if key in self.names:
            return self.names[key]
        words = key.split()
        for i in range(1, len(words)):
            tail = self.names.get(" ".join(words[i:]))
            if tail and tail.get("gloss"):
                mod = " ".join(words[:i] + ([tail["modifier"]] if tail.get("modifier") else []))
                return {**tail, "modifier": mod}
        return None

    def text(self, name: str, hypernyms: int = 2) -> str:
        e = self.entry(name)
        return entry_text(name, e, hypernyms) if e else name

    def imagenet_texts(self, hypernyms: int = 2) -> list[str]:
        return [entry_text(e["name"], e, hypernyms) for e in self.imagenet]


def load_knowledge(path: str | Path | None = None) -> Knowledge:
    """Read and check the knowledge file; a missing or corrupt file raises KnowledgeError."""
    p = Path(path) if path else DEFAULT_PATH
    return _load(str(p))


@lru_cache(maxsize=4)
def _load(p: str) -> Knowledge:
    if not Path(p).is_file():
        raise KnowledgeError(f"name knowledge file not found: {p} (rebuild: python scripts/knowledge_build.py)")
    try:
        data = json.loads(Path(p).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise KnowledgeError(f"name knowledge file {p} is not valid JSON: {exc}") from None
    return Knowledge(data, p)

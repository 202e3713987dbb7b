"""Explicit queries: a query that names a vocabulary entry, recognised by rule (normalised words,
plurals reduced) and, given a text model, by bare-text similarity (a misspelt name). Similarity
alone cannot separate the two kinds: implicit descriptions reach 0.69 to their name."""
from __future__ import annotations

import re

EXPLICIT_SIMILARITY = 0.80      # bare query vs bare name; implicit descriptions reach 0.69
EXPLICIT_MAX_EXTRA = 3          # words besides a contained name ("pick up the apple on the left")
_FILLER = {"the", "a", "an", "this", "that", "these", "those", "some", "my", "your", "please", "one"}


def _singular(w: str) -> str:
    if len(w) > 4 and w.endswith("ies"):
        return w[:-3] + "y"
    if len(w) > 3 and w.endswith("es") and w[:-2].endswith(("s", "x", "ch", "sh")):
        return w[:-2]
    if len(w) > 3 and w.endswith("s") and not w.endswith(("ss", "us", "is")):
        return w[:-1]
    return w


def normalise(text: str) -> tuple[str, ...]:
    """Lower-case words without punctuation, determiners or plural endings."""
    return tuple(_singular(w) for w in re.findall(r"[a-z0-9]+", text.lower()) if w not in _FILLER)


def _contains(hay: tuple[str, ...], needle: tuple[str, ...]) -> bool:
    n = len(needle)
    return n > 0 and any(hay[i:i + n] == needle for i in range(len(hay) - n + 1))


def explicit_match(query: str, vocabulary: list[str]) -> list[str]:
    """Vocabulary names the query names by rule, best first: exact (normalised), the query is the
    head noun of a name ("mug" -> "coffee mug"), or a name inside a short query ("pick up the
    coffee mugs"). Longer names win over shorter ones ("orange cup" over "orange")."""
    q = normalise(query)
    if not q:
        return []
    full: list[tuple[int, str]] = []   # the whole name is in the query: (length, name)
    head: list[str] = []               # the query is the end of a longer name
    for name in vocabulary:
        n = normalise(name)
        if not n:
            continue
        if q == n or (_contains(q, n) and len(q) - len(n) <= EXPLICIT_MAX_EXTRA):
            full.append((len(n), name))
        elif len(q) < len(n) and n[-len(q):] == q:
            head.append(name)
    if full:
        longest = max(k for k, _ in full)
        return [name for k, name in full if k == longest]
    return head


def is_explicit(query: str, vocabulary: list[str], text_model=None) -> bool:
    """True when the query names a vocabulary entry (rules of `explicit_match`, or a bare-text
    similarity >= EXPLICIT_SIMILARITY when a text model is given, e.g. a misspelt name)."""
    if explicit_match(query, vocabulary):
        return True
    if text_model is None:
        return False
    sims = text_model([query]) @ text_model(list(vocabulary)).T
    return float(sims.max()) >= EXPLICIT_SIMILARITY

"""A minimal reader of the Princeton WordNet 3.0 noun database (the files Debian's `wordnet-base`
installs under /usr/share/wordnet: index.noun, data.noun, noun.exc).

Only the build of the name-knowledge file (knowledge_build.py) and its test use it: run time reads
the committed JSON and needs no WordNet. A reader of our own (about 80 lines) instead of nltk or
`wn`: the format is simple and documented (wndb(5WN)), and neither package is a dependency.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

DEFAULT_DIRS = ("/usr/share/wordnet",)
# Lexicographer files (lexnames(5WN)) a table-top object's sense lives in, best first.
LEXFILE = {3: "Tops", 4: "act", 5: "animal", 6: "artifact", 7: "attribute", 8: "body", 9: "cognition",
           10: "communication", 11: "event", 12: "feeling", 13: "food", 14: "group", 15: "location",
           16: "motive", 17: "object", 18: "person", 19: "phenomenon", 20: "plant", 21: "possession",
           22: "process", 23: "quantity", 24: "relation", 25: "shape", 26: "state", 27: "substance", 28: "time"}


@dataclass
class Synset:
    offset: int
    lexfile: str
    lemmas: list[str]                       # spaces, not underscores
    gloss: str                              # definition without the quoted examples
    hypernyms: list[int] = field(default_factory=list)  # @ and @i pointers

    @property
    def wnid(self) -> str:                  # ImageNet's synset id
        return f"n{self.offset:08d}"


def find_dir(candidates=DEFAULT_DIRS) -> Path | None:
    for d in candidates:
        if (Path(d) / "data.noun").is_file() and (Path(d) / "index.noun").is_file():
            return Path(d)
    return None


def _clean_gloss(g: str) -> str:
    """'def; "example"; "example"' -> 'def' (examples are usage, not meaning)."""
    parts = [p.strip() for p in g.split(";")]
    return "; ".join(p for p in parts if p and not p.startswith('"')).strip()


class WordNet:
    def __init__(self, root: str | Path):
        root = Path(root)
        for f in ("index.noun", "data.noun"):
            if not (root / f).is_file():
                raise FileNotFoundError(f"WordNet noun database: {root / f} missing (apt-get install wordnet-base)")
        self.index: dict[str, list[int]] = {}
        for line in (root / "index.noun").read_text(encoding="latin-1").splitlines():
            if line.startswith(" "):
                continue
            t = line.split()
            n_ptr = int(t[3])
            self.index[t[0]] = [int(x) for x in t[6 + n_ptr:]]
        self.data = (root / "data.noun").read_bytes()
        self.exc: dict[str, str] = {}
        if (root / "noun.exc").is_file():
            for line in (root / "noun.exc").read_text(encoding="latin-1").splitlines():
                t = line.split()
                if len(t) >= 2:
                    self.exc[t[0]] = t[1]
        self._cache: dict[int, Synset] = {}

    def synset(self, offset: int) -> Synset:
        if offset in self._cache:
            return self._cache[offset]
        end = self.data.index(b"\n", offset)
        line = self.data[offset:end].decode("latin-1")
        head, _, gloss = line.partition(" | ")
        t = head.split()
        if int(t[0]) != offset:
            raise ValueError(f"data.noun: no synset at byte offset {offset}")
        n_words = int(t[3], 16)
        lemmas = [re.sub(r"\(.*\)$", "", t[4 + 2 * i]).replace("_", " ") for i in range(n_words)]
        k = 4 + 2 * n_words
        n_ptr = int(t[k])
        hyper = []
        for i in range(n_ptr):
            sym, off, pos = t[k + 1 + 4 * i: k + 4 + 4 * i]
            if sym in ("@", "@i") and pos == "n":
                hyper.append(int(off))
        s = Synset(offset, LEXFILE.get(int(t[1]), t[1]), lemmas, _clean_gloss(gloss), hyper)
        self._cache[offset] = s
        return s

    def senses(self, lemma: str) -> list[Synset]:
        """Noun senses of a lemma, most frequent first (index.noun order); plural forms are
        reduced by noun.exc and the regular endings, as WordNet's morphy does."""
        key = lemma.strip().lower().replace(" ", "_")
        for form in self._forms(key):
            if form in self.index:
                return [self.synset(o) for o in self.index[form]]
        return []

    def _forms(self, w: str) -> list[str]:
        out = [w, self.exc.get(w, w)]
        for suf, rep in (("ses", "s"), ("xes", "x"), ("zes", "z"), ("ches", "ch"), ("shes", "sh"), ("men", "man"),
                         ("ies", "y"), ("s", "")):
            if w.endswith(suf):
                out.append(w[: len(w) - len(suf)] + rep)
        return list(dict.fromkeys(out))

    def chain(self, s: Synset, depth: int = 3) -> list[Synset]:
        """The first-hypernym chain above a synset, nearest first."""
        out, cur = [], s
        while cur.hypernyms and len(out) < depth:
            cur = self.synset(cur.hypernyms[0])
            out.append(cur)
        return out

"""The rule parser of relational queries: text -> `Relational` (target, colour, relation to anchors,
superlative, ordinal, counting, "all"), or None for a plain name or a description.

It reads: "how many X [relation]", "all the X [relation]", "the biggest / smallest / tallest /
shortest / highest / lowest X", "the X nearest to me / the camera", "the second X from the left",
"the leftmost X", "the X on the left", "the X closest to / next to / near / beside the Y", "the X
between the Y and the Z", "the X left of / right of / in front of / behind the Y", "the X on / on top
of / under / above the Y", and colour words before the target ("the red cup"); lead-ins ("show me",
"where is"), "please" and articles around them. relations.py answers what it reads.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from functools import lru_cache

from ..perception.colour_names import COLOUR_TERMS

ANY = ("object", "thing", "item", "one", "objects", "things", "items", "whatever", "something", "anything", "stuff",
       "what", "which", "which one")
SUPERLATIVES = {"biggest": "biggest", "largest": "biggest", "smallest": "smallest", "tiniest": "smallest",
                "tallest": "tallest", "highest": "highest", "shortest": "shortest", "lowest": "lowest"}
RELATIONS = {"closest to": "near", "nearest to": "near", "next to": "near", "near": "near", "beside": "near",
             "right next to": "near", "right beside": "near", "just next to": "near",
             "close to": "near", "to the left of": "left", "left of": "left", "to the right of": "right",
             "right of": "right", "on the left of": "left", "on the right of": "right", "in front of": "front",
             "behind": "behind", "between": "between", "in between": "between",
             "on top of": "on", "on": "on", "sitting on": "on", "resting on": "on", "lying on": "on",
             "standing on": "on", "atop": "on", "under": "under", "underneath": "under", "beneath": "under",
             "below": "under", "above": "above", "over": "above"}
_REL_RE = "|".join(sorted((re.escape(k) for k in RELATIONS), key=len, reverse=True))
# words common in descriptions ("the fruit that fell on Newton's head"): these relations only between
# short noun phrases without a clause
LOOSE = {"on", "under", "above"}
CLAUSE = {"that", "which", "who", "to", "for", "with", "you", "i", "can", "used", "when", "where", "what", "at", "in",
          "of", "by", "from", "it", "goes", "fell", "put", "turns"}
ORDINALS = {"first": 1, "1st": 1, "second": 2, "2nd": 2, "third": 3, "3rd": 3, "fourth": 4, "4th": 4, "fifth": 5,
            "5th": 5, "sixth": 6, "6th": 6, "last": -1}
LEAD_IN = (r"^(?:can you |could you )?(?:show me |find |give me |point (?:to|at) |locate |where (?:is|are) "
           r"|where's |which is |what is |what's |pick up |grab |get me |hand me |see )?")
CAMERA_WORDS = ("me", "the camera", "camera", "you", "the robot", "us")


@dataclass
class Relational:
    """A parsed relational query."""

    target: str                        # the name sought; "" = any object
    colour: str = ""                   # a basic colour term the target must have
    relation: str = ""                 # near | left | right | front | behind | between
    anchors: list[str] = field(default_factory=list)
    superlative: str = ""              # biggest | smallest | tallest | shortest | highest | lowest | nearest_camera
    count: bool = False
    ordinal: int = 0                   # the Nth from `side` (-1: the last)
    side: str = ""                     # left | right (with ordinal)
    every: bool = False                # "all the X": every match
    note: str = field(default="", compare=False)   # how it was parsed, when not by the rules alone

    @property
    def attribute_only(self) -> bool:
        return not (self.relation or self.superlative or self.count or self.ordinal or self.every)

    def describe(self) -> str:
        parts = [f"target: {self.target or 'any object'}"]
        if self.colour:
            parts.append(f"colour: {self.colour}")
        if self.relation:
            parts.append(f"relation: {self.relation} " + " and ".join(repr(a) for a in self.anchors))
        if self.superlative:
            parts.append(f"superlative: {self.superlative.replace('_', ' ')}")
        if self.ordinal:
            parts.append(f"ordinal: {'last' if self.ordinal < 0 else _nth(self.ordinal)} from the {self.side}")
        if self.count:
            parts.append("count")
        if self.every:
            parts.append("all matches")
        if self.note:
            parts.append(self.note)
        return "; ".join(parts)


def _nth(n: int) -> str:
    return f"{n}{'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')}"


def _strip(phrase: str) -> str:
    p = re.sub(r"^(which|what|whichever|whatever)\s+(?=\w+ (is|are)$|\w+$)", "", phrase.strip(" ?.!,"))
    p = re.sub(r"\s+(is|are)$", "", p)
    p = re.sub(r"^(the|a|an|any|all( the)?)\s+", "", p)
    return re.sub(r"\s+(are there|is there|(?:do|can) you (?:see|find)|do you have|you can see|"
                  r"(?:are |is )?in the (scene|map|room))$", "", p).strip()


def _target(phrase: str) -> tuple[str, str]:
    """'red cup' -> ('cup', 'red'); 'object' -> ('', '')."""
    words = _strip(phrase).split()
    colour = words.pop(0) if len(words) > 1 and words[0] in COLOUR_TERMS else ""
    name = " ".join(words)
    return ("" if name in ANY else _singular(name)), colour


IRREGULAR = {"knives": "knife", "leaves": "leaf", "shelves": "shelf", "halves": "half", "loaves": "loaf",
             "mice": "mouse", "people": "person", "children": "child", "teeth": "tooth", "feet": "foot"}


def _singular(name: str) -> str:
    head, _, last = name.rpartition(" ")
    if last in IRREGULAR:
        return f"{head} {IRREGULAR[last]}".strip()
    if name.endswith("ies"):
        return name[:-3] + "y"
    if name.endswith(("ches", "shes", "xes", "ses")):
        return name[:-2]
    return name[:-1] if name.endswith("s") and not name.endswith("ss") else name


def is_thing_name(name: str, vocabulary=()) -> bool:
    """Whether `name` names a thing rather than describes one: a short noun phrase (at most three
    words, letters only, no clause word) that is a name of `vocabulary` or vocabulary.HOUSEHOLD, a
    name the WordNet knowledge holds (perception/knowledge.py; with modifiers: "striped mug") or
    one of its categories ("fruit", "hand tool"). "banana", "giraffe" are names; "small metal
    scoop", "squeezing tool, with a long bar" descriptions."""
    from .vocabulary import HOUSEHOLD

    name = _singular(" ".join(str(name).lower().split()))
    words = name.split()
    if not re.fullmatch(r"[a-z][a-z' -]*", name) or len(words) > 3 or set(words) & CLAUSE:
        return False
    if name in {_singular(str(v).lower()) for v in (*vocabulary, *HOUSEHOLD)}:
        return True
    from ..perception.knowledge import KnowledgeError, load_knowledge

    try:
        return load_knowledge().entry(name) is not None or name in _categories()
    except KnowledgeError:
        return False


@lru_cache(maxsize=1)
def _categories() -> frozenset[str]:
    """The knowledge's hypernyms and their head nouns ("edible fruit", "fruit")."""
    from ..perception.knowledge import load_knowledge

    hyp = {h.lower() for e in load_knowledge().names.values() for h in e.get("hypernyms", [])}
    return frozenset(hyp | {h.split()[-1] for h in hyp})


POSSESSIVES = ("my", "our", "your", "his", "her", "their", "the", "this", "that", "a", "an", "these", "those")


def core_name(name: str) -> str:
    """Without case, leading possessives or articles and a plural: what spellings of one name
    share ("My Mugs" -> "mug")."""
    words = str(name).lower().replace("'s ", " ").split()
    while len(words) > 1 and words[0] in POSSESSIVES:
        words.pop(0)
    return _singular(" ".join(words)) if words else ""


def names_match(query: str, name: str) -> bool:
    """Whether `query` names the taught `name`: the same core name ("my blue mugs" is "blue mug"),
    or the taught name ends in the query as a word ("mug" finds "blue mug"). A query more specific
    than the name is not it: "red cup" is not the object taught as "cup" (the scene may hold
    several cups, and the untaught red one must not answer as the taught one)."""
    q, n = core_name(query), core_name(name)
    return bool(q) and (q == n or n.endswith(" " + q))


def _relation(text: str) -> Relational | None:
    """'cups (that are) next to the laptop' -> Relational, or None."""
    m = re.fullmatch(r"(?P<t>.+?) (?:(?:that|which) )?(?:(?:is|are|sits|sit|lies|lie|stands|stand|rests|rest)"
                     r"(?: sitting| lying| standing| resting)? )?(?P<r>" + _REL_RE +
                     r") (?P<a>.+?)(?: and (?P<b>.+))?", text)
    if not m:
        return None
    sup = re.match(r"(?:the |a |an )?(" + "|".join(SUPERLATIVES) + r") ", m["t"])   # "the biggest cup on the table"
    t, c = _target(m["t"][sup.end():] if sup else m["t"])
    rel = RELATIONS[m["r"]]
    anchors = [_strip(m["a"])] + ([_strip(m["b"])] if m["b"] else [])
    if rel == "between" and len(anchors) != 2:
        return None
    if rel != "between" and m["b"]:
        anchors = [_strip(m["a"] + " and " + m["b"])]
    if rel in LOOSE and (len(_strip(m["t"]).split()) > 3 or set(_strip(m["t"]).split()) & CLAUSE
                         or any(len(a.split()) > 3 or set(a.split()) & CLAUSE for a in anchors)):
        return None
    if rel == "near" and anchors[0] in CAMERA_WORDS:
        return Relational(t, c, superlative="nearest_camera")
    if not all(anchors):
        return None
    return Relational(t, c, rel, [_singular(a) for a in anchors], superlative=SUPERLATIVES[sup[1]] if sup else "")


def _normalise(query: str) -> str:
    """Lower case, single spaces, without end punctuation, "please" or a lead-in ("show me")."""
    q = " ".join(query.lower().split()).strip(" ?.!")
    q = re.sub(r"^please,? |,? please$", "", q).strip(" ?.!,")
    return re.sub(LEAD_IN, "", q)


def bare_name(query: str, vocabulary: list[str]) -> str | None:
    """The vocabulary name a query asks for with only an article, a lead-in or "please" around it
    ("pick up the blue cup, please" -> "blue cup"), else None."""
    q = re.sub(r"^(the|a|an)\s+", "", _normalise(query))
    return {v.lower(): v for v in vocabulary}.get(q)


def parse(query: str) -> Relational | None:
    """A relational query, or None when the query is a plain name or description."""
    q = _normalise(query)
    q = re.sub(r"^(?:what's|whats|what|which one is|which)\s+(?=(?:(?:is|are) )?(?:" + _REL_RE + r") )", "", q)
    if re.match(r"(?:(?:is|are) )?(?:" + _REL_RE + r") ", q):   # "what's next to the X": any object
        q = "object " + q
    m = re.fullmatch(r"(?:how many|count(?: the)?) (?P<t>.+)", q)
    if m:
        rest = _strip(m["t"])
        rq = _relation(rest) or Relational(*_target(rest))
        rq.count = True
        return rq
    m = re.fullmatch(r"(?:all(?: of)?|every|each)(?: the)? (?P<t>.+)", q)
    if m:
        rq = _relation(m["t"]) or Relational(*_target(m["t"]))
        rq.every = True
        return rq
    m = re.fullmatch(r"(?:the )?(?P<n>" + "|".join(ORDINALS) + r") (?P<t>.+?) (?:from|on) the (?P<s>left|right)", q)
    if m:
        return Relational(*_target(m["t"]), ordinal=ORDINALS[m["n"]], side=m["s"])
    m = re.fullmatch(r"(?:the )?(?P<s>left|right)most (?P<t>.+)", q) or \
        re.fullmatch(r"(?P<t>.+?)(?: that| which)?(?: is| are)? on the (?:far )?(?P<s>left|right)(?: side)?", q)
    if m:
        return Relational(*_target(m["t"]), ordinal=1, side=m["s"])
    m = re.fullmatch(r"(?:the |a |an )?(?P<s>" + "|".join(SUPERLATIVES) + r"|nearest|closest) (?P<t>.+?)"
                     r"(?: (?:to|from) (?:me|the camera|the robot|you))?", q)
    if m and not re.search(r" (?:" + _REL_RE + r") ", f" {m['t']} "):
        t, c = _target(m["t"])
        sup = "nearest_camera" if m["s"] in ("nearest", "closest") else SUPERLATIVES[m["s"]]
        return Relational(t, c, superlative=sup)
    rq = _relation(q)
    if rq is not None:
        return rq
    t, c = _target(q)
    if c and len(q.split()) <= 4:   # "the red cup": a colour and a name (callers check it is not one name)
        return Relational(t, c)
    return None


# ------------------------------------------------------------------------------ the LLM parser option

_REL_NAMES = sorted(set(RELATIONS.values()))
_SUP_NAMES = sorted(set(SUPERLATIVES.values()) | {"nearest_camera"})
LLM_PARSE_PROMPT = (
    "You turn a request for objects in a 3D scene into JSON. Reply with one JSON object and nothing else, "
    "with the keys: target (the object name sought, singular, no article; \"\" for any object), colour (one of "
    f"{json.dumps(list(COLOUR_TERMS))} or \"\"), relation (one of {json.dumps(_REL_NAMES)} or \"\"), anchors "
    "(the names of the objects the relation refers to: two for between, one for the others, none without a "
    f"relation), superlative (one of {json.dumps(_SUP_NAMES)} or \"\"), ordinal (N for the Nth from the left or "
    "right, -1 for the last, 1 for leftmost or rightmost, else 0), side (\"left\", \"right\" or \"\"), count (true "
    "for how many), every (true for all the ...). Example: \"the second red cup from the left\" -> "
    '{"target": "cup", "colour": "red", "relation": "", "anchors": [], "superlative": "", "ordinal": 2, '
    '"side": "left", "count": false, "every": false}.')
LLM_PARSE_SCHEMA = {
    "type": "object",
    "required": ["target", "colour", "relation", "anchors", "superlative", "ordinal", "side", "count", "every"],
    "properties": {"target": {"type": "string"}, "colour": {"type": "string", "enum": ["", *COLOUR_TERMS]},
                   "relation": {"type": "string", "enum": ["", *_REL_NAMES]},
                   "anchors": {"type": "array", "items": {"type": "string"}, "maxItems": 2},
                   "superlative": {"type": "string", "enum": ["", *_SUP_NAMES]},
                   "ordinal": {"type": "integer", "minimum": -1, "maximum": 20},
                   "side": {"type": "string", "enum": ["", "left", "right"]},
                   "count": {"type": "boolean"}, "every": {"type": "boolean"}}}


def from_fields(data: dict) -> Relational | None:
    """An LLM parser's JSON answer (LLM_PARSE_SCHEMA) -> Relational, checked as strictly as the rule
    parser's own output; None when it asks for a plain name or description. ValueError says what
    was wrong (the caller then falls back to `parse`)."""
    if not isinstance(data, dict):
        raise ValueError(f"expected a JSON object, got {type(data).__name__}")
    props = LLM_PARSE_SCHEMA["properties"]
    unknown = sorted(set(data) - set(props))
    if unknown:
        raise ValueError(f"unknown key(s) {unknown}; expected {sorted(props)}")
    kinds = {"string": str, "boolean": bool, "array": list}
    for key, spec in props.items():
        v = data.get(key, {"string": "", "array": [], "boolean": False, "integer": 0}[spec["type"]])
        ok = (type(v) is int) if spec["type"] == "integer" else isinstance(v, kinds[spec["type"]])
        if not ok:
            raise ValueError(f"{key} is {type(v).__name__} {v!r}, expected {spec['type']}")
        if "enum" in spec and v not in spec["enum"]:
            raise ValueError(f"{key} {v!r} is not one of {spec['enum'][1:]}")
        data = {**data, key: v}
    if not -1 <= data["ordinal"] <= 20:
        raise ValueError(f"ordinal {data['ordinal']} is outside -1..20")
    anchors = [_singular(_strip(a.lower())) if isinstance(a, str) else "" for a in data["anchors"]]
    if not all(anchors):
        raise ValueError(f"anchors must be object names, got {data['anchors']!r}")
    need = 2 if data["relation"] == "between" else 1 if data["relation"] else 0
    if len(anchors) != need:
        raise ValueError(f"relation {data['relation'] or 'none'!r} takes {need} anchor(s), got {len(anchors)}")
    if bool(data["ordinal"]) != bool(data["side"]):
        raise ValueError(f"ordinal {data['ordinal']} and side {data['side']!r} go together")
    target = _strip(data["target"].lower())
    if len(target) > 100:
        raise ValueError(f"target of {len(target)} characters is not an object name")
    rq = Relational("" if target in ANY else _singular(target), data["colour"], data["relation"], anchors,
                    data["superlative"], data["count"], data["ordinal"], data["side"], data["every"])
    return None if rq.attribute_only and not rq.colour else rq


def _check_words_in(rq: Relational | None, query: str) -> None:
    """ValueError unless the parse's target, anchors and colour are words of the query (singular
    or plural): a model that answers with names the query never said (a small one copies its
    prompt's example) has not read it."""
    from ..perception.reasoning.explicit import normalise

    if rq is None:
        return
    words = f" {' '.join(normalise(query))} "
    for what, name in [("target", rq.target), ("colour", rq.colour)] + [("anchor", a) for a in rq.anchors]:
        n = " ".join(normalise(name))
        if n and f" {n} " not in words:
            raise ValueError(f"{what} {name!r} is not in the query")


def parse_with(reasoner, query: str) -> tuple[Relational | None, str]:
    """(parse, how it was parsed): the reasoner's LLM when it has one (`ask_json`), else or when its
    answer is unusable, the rule parser; the note goes into the explanation."""
    if not hasattr(reasoner, "ask_json"):
        return parse(query), ""
    try:
        rq, note = from_fields(reasoner.ask_json(LLM_PARSE_PROMPT, query, LLM_PARSE_SCHEMA)), f"parsed by the {reasoner.name} model"
        _check_words_in(rq, query)
    except Exception as exc:  # noqa: BLE001 - any failure of the model means: the rule parser
        why = reasoner.describe(exc) if hasattr(reasoner, "describe") else f"{type(exc).__name__}: {exc}"
        rq, note = parse(query), f"{reasoner.name} parse unusable ({why}); parsed by rules"
    if rq is not None:
        rq.note = note
    return rq, note

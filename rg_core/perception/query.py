"""What a query and its mode must be, checked in one place: the node, the worker, the CLI, the
Grounder and the reasoners all call these, so a bad request gets the same answer everywhere."""
from __future__ import annotations

MODES = ("auto", "explicit", "implicit")


def query_problem(query, max_chars: int) -> str | None:
    """Why `query` cannot be grounded (what was wrong, what is expected), or None."""
    if not isinstance(query, str):
        return f"query must be a string, got {type(query).__name__}"
    if not query.strip():
        return "empty query: say what to find, e.g. 'the red mug'"
    if len(query) > max_chars:
        return f"query is {len(query)} characters long; at most {max_chars} are accepted (max_query_chars)"
    if not any(c.isalnum() for c in query):
        return f"query holds no letters or digits ({query[:20]!r}): say what to find, e.g. 'the red mug'"
    return None


def check_query(query, max_chars: int) -> str:
    """`query` unchanged, or ValueError with query_problem's message."""
    problem = query_problem(query, max_chars)
    if problem:
        raise ValueError(problem)
    return query


def parse_mode(mode) -> str:
    """A request's mode -> one of MODES: case and surrounding space ignored, empty = auto."""
    m = (mode or "").strip().lower() if isinstance(mode, str) else mode
    m = m or "auto"
    if m not in MODES:
        raise ValueError(f"mode must be one of {', '.join(MODES)} (empty = auto), got {mode!r}")
    return m

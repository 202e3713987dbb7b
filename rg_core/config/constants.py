"""Project-wide values the sections' defaults and the library share."""
from __future__ import annotations

# Where the project keeps what it derives once per machine (embeddings, fixed URDFs; models/ below it).
CACHE_DIR = "~/.cache/reasongrounder"
MAX_QUERY_CHARS = 1000   # longer queries are refused (the node, the Grounder and every reasoner)

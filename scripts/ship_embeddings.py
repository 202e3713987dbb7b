"""Build the text embeddings the package ships (rg_core/perception/data/embeddings/): the offline
text reasoner's background names and glosses and ConSE's ImageNet class names, embedded with the
packaged MiniLM. They depend only on packaged models and files, so a fresh machine's first query
and first supervision read them instead of embedding about 3000 texts (10-20 s on 2 cores).

Run after changing the knowledge file, the background lists or the encoder:
    python scripts/ship_embeddings.py
tests/test_knowledge.py checks that the shipped files match what the code would compute.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rg_core.perception.embed import make_embedder  # noqa: E402
from rg_core.perception.reasoning import TextReasoner  # noqa: E402
from rg_core.perception.text_cache import SHIPPED_DIR  # noqa: E402


def main() -> None:
    SHIPPED_DIR.mkdir(parents=True, exist_ok=True)
    for old in SHIPPED_DIR.glob("*.npy"):
        old.unlink()   # stale keys would never be read again
    TextReasoner(cache_dir=str(SHIPPED_DIR)).background()
    make_embedder("conse", cache_dir=str(SHIPPED_DIR))
    for p in sorted(SHIPPED_DIR.glob("*.npy")):
        print(f"{p.relative_to(SHIPPED_DIR.parents[3])}: {p.stat().st_size / 1e6:.2f} MB")


if __name__ == "__main__":
    main()

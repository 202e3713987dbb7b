"""A hub-shaped HTTP server on 127.0.0.1 for the `rg models` tests, and the tiny repositories it serves.

It answers what huggingface_hub asks of the real hub (as far as hf_hub_download needs):
- HEAD/GET /{repo}/resolve/{revision}/{file}: X-Repo-Commit, ETag. Small text files are served
  directly with their git blob sha1 as ETag; LFS files (weights) answer 302 with X-Linked-Etag (the
  file's SHA-256), X-Linked-Size and an absolute Location on /lfs/{sha256}, as the hub redirects to
  its CDN. A missing file answers 404 with X-Error-Code: EntryNotFound; a missing repository
  RepoNotFound.
- GET with Range: bytes=N- answers 206 with Content-Range (resumed downloads).
- /api/models/{repo}/revision/{rev} (id, sha, siblings) and /api/models/{repo}/tree/{rev} (files with
  their git and LFS hashes): what snapshot_download lists.
Faults for tests: `drop_once` (file names whose first full GET sends half the body, then closes the
connection), `corrupt` (file names served with one byte flipped while the headers keep the true hash).
Every request is logged as (method, path, Range header).

The repositories hold tiny random-weight models built with the real architectures at reduced width
(transformers' CLIPModel converted to OpenCLIP's layout, transformers' SamModel), saved under the
file names of the real repositories.
"""
from __future__ import annotations

import hashlib
import json
import re
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

LFS_SUFFIXES = (".safetensors", ".bin", ".gguf", ".onnx", ".pt")


class HubRepo:
    def __init__(self, repo_id: str, files: dict[str, bytes], commit: str | None = None):
        self.repo_id, self.files = repo_id, files
        self.commit = commit or hashlib.sha1(repo_id.encode()).hexdigest()

    @staticmethod
    def git_sha1(data: bytes) -> str:
        return hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()


class HubServer:
    def __init__(self):
        self.repos: dict[str, HubRepo] = {}
        self.blobs: dict[str, bytes] = {}
        self.drop_once: set[str] = set()
        self.corrupt: set[str] = set()
        self.log: list[tuple[str, str, str | None]] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *a):
                pass

            def do_HEAD(self):
                server._handle(self, head=True)

            def do_GET(self):
                server._handle(self, head=False)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        # LFS redirects go to another host name (the real hub sends them to its CDN); huggingface_hub
        # then takes the metadata from the redirect itself instead of following it.
        self.cdn_url = f"http://localhost:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def add(self, repo: HubRepo, alias_commits: tuple[str, ...] = ()) -> None:
        self.repos[repo.repo_id] = repo
        for data in repo.files.values():
            self.blobs[hashlib.sha256(data).hexdigest()] = data

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.httpd.shutdown()
        self.httpd.server_close()

    # ------------------------------------------------------------------------------ requests

    def _send(self, h, status: int, headers: dict, body: bytes = b"", head: bool = False, cut: int | None = None):
        h.send_response(status)
        for k, v in headers.items():
            h.send_header(k, str(v))
        if "Content-Length" not in headers:
            h.send_header("Content-Length", str(len(body)))
        h.end_headers()
        if head:
            return
        if cut is not None:  # a dropped connection: part of the body, then close
            h.wfile.write(body[:cut])
            h.wfile.flush()
            h.close_connection = True
            h.connection.shutdown(2)
            return
        h.wfile.write(body)

    def _error(self, h, status: int, code: str, msg: str, head: bool):
        body = json.dumps({"error": msg}).encode()
        self._send(h, status, {"X-Error-Code": code, "X-Error-Message": msg, "Content-Type": "application/json"},
                   body, head)

    def _body(self, h, name: str, data: bytes, etag: str, extra: dict, head: bool):
        rng = h.headers.get("Range")
        served = data
        if name in self.corrupt and data:
            served = bytes([data[0] ^ 0xFF]) + data[1:]
        headers = {"ETag": f'"{etag}"', "Accept-Ranges": "bytes", "Content-Type": "application/octet-stream", **extra}
        m = re.fullmatch(r"bytes=(\d+)-(\d*)", rng or "")
        if m:
            start = int(m.group(1))
            end = int(m.group(2)) if m.group(2) else len(served) - 1
            part = served[start:end + 1]
            headers.update({"Content-Range": f"bytes {start}-{start + len(part) - 1}/{len(served)}",
                            "Content-Length": len(part)})
            return self._send(h, 206, headers, part, head)
        cut = None
        if not head and name in self.drop_once:
            self.drop_once.discard(name)
            cut = len(served) // 2
        headers["Content-Length"] = len(served)
        self._send(h, 200, headers, served, head, cut)

    def _handle(self, h, head: bool):
        path = h.path.split("?")[0]
        self.log.append(("HEAD" if head else "GET", path, h.headers.get("Range")))
        m = re.fullmatch(r"/lfs/([0-9a-f]{64})/(.+)", path)
        if m:
            sha, name = m.groups()
            if sha not in self.blobs:
                return self._error(h, 404, "EntryNotFound", "no such blob", head)
            return self._body(h, name, self.blobs[sha], sha, {}, head)
        m = re.fullmatch(r"/api/models/(.+?)/revision/([^/]+)", path)
        if m:
            repo = self.repos.get(m.group(1))
            if repo is None:
                return self._error(h, 404, "RepoNotFound", "Repository not found", head)
            body = json.dumps({"id": repo.repo_id, "sha": repo.commit, "siblings": [{"rfilename": f} for f in repo.files]}).encode()
            return self._send(h, 200, {"Content-Type": "application/json", "X-Repo-Commit": repo.commit}, body, head)
        m = re.fullmatch(r"/api/models/(.+?)/tree/([^/]+)", path)
        if m:
            repo = self.repos.get(m.group(1))
            if repo is None:
                return self._error(h, 404, "RepoNotFound", "Repository not found", head)
            entries = []
            for f, data in repo.files.items():
                e = {"type": "file", "path": f, "size": len(data), "oid": HubRepo.git_sha1(data)}
                if f.endswith(LFS_SUFFIXES):
                    e["lfs"] = {"oid": hashlib.sha256(data).hexdigest(), "size": len(data), "pointerSize": 134}
                entries.append(e)
            return self._send(h, 200, {"Content-Type": "application/json"}, json.dumps(entries).encode(), head)
        m = re.fullmatch(r"/(.+?)/resolve/([^/]+)/(.+)", path)
        if not m:
            return self._error(h, 404, "RepoNotFound", "not a hub path", head)
        repo_id, rev, fname = m.groups()
        repo = self.repos.get(repo_id)
        if repo is None:
            return self._error(h, 404, "RepoNotFound", "Repository not found", head)
        commit = rev if re.fullmatch(r"[0-9a-f]{40}", rev) else repo.commit
        if fname not in repo.files:
            h_extra = {"X-Repo-Commit": commit}
            body = json.dumps({"error": "Entry not found"}).encode()
            return self._send(h, 404, {"X-Error-Code": "EntryNotFound", "X-Error-Message": "Entry not found", **h_extra},
                              body, head)
        data = repo.files[fname]
        if fname.endswith(LFS_SUFFIXES):
            sha = hashlib.sha256(data).hexdigest()
            pointer_etag = HubRepo.git_sha1(f"oid sha256:{sha}\nsize {len(data)}\n".encode())
            return self._send(h, 302, {"Location": f"{self.cdn_url}/lfs/{sha}/{fname}", "X-Repo-Commit": commit,
                                       "X-Linked-Etag": f'"{sha}"', "X-Linked-Size": len(data),
                                       "ETag": f'"{pointer_etag}"', "Content-Length": 0}, b"", head)
        return self._body(h, fname, data, HubRepo.git_sha1(data), {"X-Repo-Commit": commit}, head)


# ---------------------------------------------------------------------------------- tiny repositories

def tiny_clip_files(seed: int = 0) -> dict[str, bytes]:
    """OpenCLIP layout (open_clip_config.json, open_clip_model.safetensors, tokenizer.json) of a
    random CLIP ViT (image 32 px, patch 8, width 32, 2 layers; text width 32, 2 layers, context 16)."""
    import tempfile

    import torch
    from safetensors.torch import save
    from transformers import CLIPTokenizerFast

    from rg_core.models.clip_convert import hf_config, hf_to_openclip

    chars = "abcdefghijklmnopqrstuvwxyz"
    tokens = list(chars) + [c + "</w>" for c in chars] + ["<|startoftext|>", "<|endoftext|>"]
    oc = {"model_cfg": {"embed_dim": 24,
                        "vision_cfg": {"image_size": 32, "layers": 2, "width": 32, "patch_size": 8, "head_width": 16},
                        "text_cfg": {"context_length": 16, "vocab_size": len(tokens), "width": 32, "heads": 2, "layers": 2}},
          "preprocess_cfg": {"mean": [0.48145466, 0.4578275, 0.40821073], "std": [0.26862954, 0.26130258, 0.27577711]}}
    from transformers import CLIPModel

    torch.manual_seed(seed)
    cfg = hf_config(oc)
    model = CLIPModel(cfg).eval()
    sd = hf_to_openclip(model.state_dict(), cfg)
    with tempfile.TemporaryDirectory() as d:
        (Path(d) / "vocab.json").write_text(json.dumps({t: i for i, t in enumerate(tokens)}))
        (Path(d) / "merges.txt").write_text("#version: 0.2\n")
        tok = CLIPTokenizerFast(vocab_file=str(Path(d) / "vocab.json"), merges_file=str(Path(d) / "merges.txt"))
        tok.backend_tokenizer.save(str(Path(d) / "tokenizer.json"))
        tokenizer_json = (Path(d) / "tokenizer.json").read_bytes()
    return {"open_clip_config.json": json.dumps(oc, indent=1).encode(), "open_clip_model.safetensors": save(sd),
            "tokenizer.json": tokenizer_json, "README.md": b"tiny random CLIP for tests\n"}


def tiny_sam_files(seed: int = 0) -> dict[str, bytes]:
    """transformers SamModel layout (config.json, model.safetensors, preprocessor_config.json) of a random
    SAM (vision width 32, 2 layers, 32 channels; SAM's 1024 input and 64x64 embedding grid). The IoU
    head's last bias is set to 2 and the hypernetwork outputs are scaled up so that random masks pass
    SAM's default IoU and stability filters (an untouched random SAM yields none)."""
    import tempfile

    import torch
    from transformers import SamConfig, SamModel

    torch.manual_seed(seed)
    cfg = SamConfig(vision_config=dict(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, mlp_dim=64,
                                       output_channels=32, global_attn_indexes=[1], window_size=14, num_pos_feats=16),
                    prompt_encoder_config=dict(hidden_size=32, mask_input_channels=16),
                    mask_decoder_config=dict(hidden_size=32, mlp_dim=64, num_hidden_layers=2, num_attention_heads=2,
                                             iou_head_hidden_dim=32))
    sam = SamModel(cfg).eval()
    with torch.no_grad():
        for p in sam.parameters():  # transformers' init leaves some weights zero (e.g. the neck): all random
            if p.dim() > 1:
                p.normal_(0.0, p[0].numel() ** -0.5)
        sam.mask_decoder.iou_prediction_head.proj_out.bias.fill_(2.0)
        sam.mask_decoder.iou_prediction_head.proj_out.weight.mul_(0.01)
        for mlp in sam.mask_decoder.output_hypernetworks_mlps:
            mlp.proj_out.weight.mul_(2000.0)
    with tempfile.TemporaryDirectory() as d:
        sam.save_pretrained(d, safe_serialization=True)
        out = {n: (Path(d) / n).read_bytes() for n in ("config.json", "model.safetensors")}
    out["preprocessor_config.json"] = json.dumps({"do_normalize": True, "do_resize": True, "image_mean": [0.485, 0.456, 0.406],
                                                  "image_std": [0.229, 0.224, 0.225], "longest_edge": 1024}).encode()
    return out

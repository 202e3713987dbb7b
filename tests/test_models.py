"""`rg models` against a loopback hub-shaped server (tests/hub_server.py) that serves tiny random-weight
CLIP (OpenCLIP layout) and SAM (transformers layout) models under the real repositories' names: the
real huggingface_hub client downloads them (HF_ENDPOINT), the project's code exports and verifies them,
and `rg map --supervise` / `rg ground` use them through the "paper" preset. Also: an interrupted
download resumes, a corrupted file is caught by its checksum, offline mode with an empty cache names
the command to run."""
import hashlib
import json
import os
import subprocess
import sys

import pytest
import torch

from hub_server import HubRepo, HubServer, tiny_clip_files, tiny_sam_files
from rg_core.models import ModelError, get_spec
from rg_core.models.clip_convert import hf_config, hf_to_openclip, openclip_to_hf

CLIP, SAM = "openclip-vit-b16-laion2b", "sam-vit-huge"


@pytest.fixture(scope="module")
def repos():
    return {CLIP: tiny_clip_files(), SAM: tiny_sam_files()}


@pytest.fixture
def hub(repos):
    with HubServer() as h:
        for name, files in repos.items():
            h.add(HubRepo(get_spec(name).repo_id, files))
        yield h


def rg(*args, env=None, timeout=300):
    e = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "rg_core.cli", *args], capture_output=True, text=True, env=e,
                          timeout=timeout)


def online(hub, cache):
    return {"HF_ENDPOINT": hub.url, "HF_HUB_OFFLINE": "0", "RG_MODELS_DIR": str(cache)}


def offline(cache):
    return {"HF_HUB_OFFLINE": "1", "HF_ENDPOINT": "http://127.0.0.1:9", "RG_MODELS_DIR": str(cache)}


def test_fetch_export_verify_then_map_and_ground(hub, repos, tmp_path):
    cache = tmp_path / "models"
    r = rg("models", "fetch", CLIP, SAM, "--json", env=online(hub, cache))
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    for name in (CLIP, SAM):
        files = out[name]["files"]
        assert set(files) == {f if isinstance(f, str) else f[0] for f in get_spec(name).files}
        for fname, rec in files.items():
            data = repos[name][fname]
            assert rec["sha256"] == hashlib.sha256(data).hexdigest() == hashlib.sha256((cache / name / fname).read_bytes()).hexdigest()
    # LFS weights came through the hub's redirect to its blob store, text files directly.
    assert any(m == "GET" and p.startswith("/lfs/") for m, p, _ in hub.log)
    r = rg("models", "list", "--json", env=offline(cache))
    status = {m["name"]: m for m in json.loads(r.stdout)["models"]}
    assert status[CLIP]["status"] == status[SAM]["status"] == "fetched, not exported"
    assert status[CLIP]["next"] == f"rg models export {CLIP}" and status["llava-1.5-7b"]["status"] == "missing"

    # Everything from here on runs offline: nothing more is downloaded.
    r = rg("models", "export", CLIP, SAM, "--json", env=offline(cache))
    assert r.returncode == 0, r.stderr
    ex = json.loads(r.stdout)
    assert ex[CLIP]["image_size"] == 32 and ex[CLIP]["context_length"] == 16 and ex[CLIP]["dim"] == 24
    assert ex[SAM]["embed_dim"] == 32 and ex[SAM]["embed_size"] == 64
    r = rg("models", "verify", CLIP, SAM, "--json", env=offline(cache))
    assert r.returncode == 0, r.stderr
    v = json.loads(r.stdout)
    assert v[CLIP]["ok"] and v[CLIP]["image_embeddings"] == [3, 24] and v[CLIP]["text_embeddings"] == [3, 24]
    assert v[CLIP]["parity"]["image_max_abs"] <= 1e-4 and v[CLIP]["parity"]["text_max_abs"] <= 1e-4
    assert v[SAM]["ok"] and v[SAM]["image_embeddings"] == [1, 32, 64, 64] and v[SAM]["masks"] == [4, 3, 96, 128]
    assert v[SAM]["parity"]["logit_rel"] <= 1e-3 and v[SAM]["parity"]["iou_max_abs"] <= 1e-3
    status = {m["name"]: m["status"] for m in json.loads(rg("models", "list", "--json", env=offline(cache)).stdout)["models"]}
    assert status[CLIP] == status[SAM] == "ready"

    # The paper preset through the whole pipeline (small budgets: this checks that it runs and reports).
    scene = tmp_path / "scene"
    # 12 views: at least 8 keyframe masks (one per keyframe from this random SAM) fit the PCA the field needs.
    r = rg("synth", str(scene), "--views", "12", "--size", "160x120", "--seed", "3", "--objects", "3", "--workers", "1",
           "--json")
    assert r.returncode == 0, r.stderr
    cfg = tmp_path / "rg.yaml"
    cfg.write_text("map:\n  iters_per_keyframe: 3\n  final_iters: 0\nmodels:\n  sam_points_per_side: 3\n"
                   "  sam_points_per_batch: 16\n  threads: 1\n")
    r = rg("--config", str(cfg), "map", str(scene), "--out", str(tmp_path / "m.rgmap"), "--supervise", "--train-field", "2",
           "--preset", "paper", "--quiet", "--json", env=offline(cache))
    assert r.returncode == 0, r.stderr
    m = json.loads(r.stdout)
    assert m["supervision"]["preset"] == "paper" and m["field"]["steps"] > 0
    assert m["supervision"]["masks_per_keyframe"] > 0 and m["supervision"]["pca"]["fitted_on"] >= 8, m["supervision"]
    r = rg("--config", str(cfg), "ground", str(tmp_path / "m.rgmap"), "a red box", "--preset", "paper", "--backend",
           "text", "--name", "red box", "--json", env=offline(cache))
    assert r.returncode == 0, r.stderr
    g = json.loads(r.stdout)
    assert g["query"] == "a red box" and isinstance(g["success"], bool) and g["message"]
    # rg eval on that map with the preset: queries embedded by the preset's CLIP text tower (LLaVA absent: warned).
    r = rg("--config", str(cfg), "eval", str(scene), "--map", str(tmp_path / "m.rgmap"), "--preset", "paper",
           "--field-seconds", "0", "--implicit", "0", "--quiet", "--json", env=offline(cache))
    assert r.returncode == 0, r.stderr
    assert "rg models fetch llava-1.5-7b" in r.stderr and json.loads(r.stdout)["eval"]
    # The node's worker with the preset's perception grounds in the same space (CLIP text, 24-d).
    from rg_core.config import load_config
    from rg_core.map.store import load_map
    from rg_core.models import make_perception
    from rg_ros.worker import MapWorker, WorkerConfig

    wc = load_config(cfg)
    wc.models.dir, wc.reason.backend = str(cache), "text"
    worker = MapWorker(wc, WorkerConfig(), load_map(tmp_path / "m.rgmap"),
                       perception_loader=lambda: make_perception("paper", wc.models))
    worker._load_perception_thread()
    assert worker.perception_state == "ready" and worker._perception[1].name == "onnx_clip"
    res = worker.ground("a red box")
    assert res.query == "a red box" and res.message and "dimension" not in res.message.lower(), res.message
    assert worker._reader.encode(["a red box"]).shape == (1, 24)   # the queries' Grounder (reads.py)
    # Without --backend the paper preset reasons with LLaVA, which was not fetched: the error says how to get it.
    r = rg("--config", str(cfg), "ground", str(tmp_path / "m.rgmap"), "something to drink from", "--preset", "paper",
           "--json", env=offline(cache))
    assert r.returncode == 2 and "rg models fetch llava-1.5-7b" in json.loads(r.stdout)["error"]


def test_interrupted_download_resumes(repos, tmp_path):
    from safetensors.torch import load, save

    # huggingface_hub writes 10 MiB chunks: the weights get an extra 24 MB tensor (ignored by the
    # conversion, as extra keys of real checkpoints are) so that a cut after half the body leaves a
    # partial file to resume from.
    files = dict(repos[CLIP])
    files["open_clip_model.safetensors"] = save({**load(files["open_clip_model.safetensors"]),
                                                 "padding": torch.arange(6_000_000, dtype=torch.float32)})
    with HubServer() as hub:
        hub.add(HubRepo(get_spec(CLIP).repo_id, files))
        hub.drop_once.add("open_clip_model.safetensors")
        r = rg("models", "fetch", CLIP, "--json", env=online(hub, tmp_path))
    assert r.returncode == 0, r.stderr
    data = files["open_clip_model.safetensors"]
    sha = hashlib.sha256(data).hexdigest()
    gets = [(p, rng) for m, p, rng in hub.log if m == "GET" and p.startswith(f"/lfs/{sha}")]
    assert len(gets) == 2 and gets[0][1] is None, gets  # the full request, cut after half the body ...
    start = int(gets[1][1].removeprefix("bytes=").rstrip("-"))
    assert 0 < start <= len(data) // 2  # ... then a Range request for the rest, not the whole file again
    assert (tmp_path / CLIP / "open_clip_model.safetensors").read_bytes() == data
    assert json.loads(r.stdout)[CLIP]["files"]["open_clip_model.safetensors"]["sha256"] == sha
    # A second fetch finds every file intact (hashes match the hub's) and downloads nothing.
    with HubServer() as hub2:
        hub2.add(HubRepo(get_spec(CLIP).repo_id, files))
        assert rg("models", "fetch", CLIP, "--json", env=online(hub2, tmp_path)).returncode == 0
    assert [p for m, p, _ in hub2.log if m == "GET" and ("/resolve/" in p or p.startswith("/lfs/"))] == [], hub2.log


def test_corrupted_file_is_caught_by_checksum(hub, repos, tmp_path):
    hub.corrupt.add("open_clip_model.safetensors")
    r = rg("models", "fetch", CLIP, "--json", env=online(hub, tmp_path))
    assert r.returncode == 2
    err = json.loads(r.stdout)["error"]
    assert "open_clip_model.safetensors: checksum mismatch" in err and f"rg models fetch {CLIP}" in err, err
    assert not (tmp_path / CLIP / "open_clip_model.safetensors").exists()  # the bad file is not kept
    hub.corrupt.clear()
    assert rg("models", "fetch", CLIP, "--json", env=online(hub, tmp_path)).returncode == 0
    # A file damaged on disk afterwards: verify refuses it, fetch replaces it.
    p = tmp_path / CLIP / "open_clip_model.safetensors"
    b = bytearray(p.read_bytes())
    b[-1] ^= 1
    p.write_bytes(bytes(b))
    r = rg("models", "verify", CLIP, "--json", env=offline(tmp_path))
    assert r.returncode == 2 and "checksum mismatch" in json.loads(r.stdout)["error"]
    assert rg("models", "fetch", CLIP, "--json", env=online(hub, tmp_path)).returncode == 0
    assert p.read_bytes() == repos[CLIP]["open_clip_model.safetensors"]


def test_alternative_weights_file_is_fetched_and_exported(repos, tmp_path):
    """A repository holding only open_clip_pytorch_model.bin (the older name) serves the same model."""
    import io

    from safetensors.torch import load

    files = {k: v for k, v in repos[CLIP].items() if k != "open_clip_model.safetensors"}
    buf = io.BytesIO()
    torch.save(load(repos[CLIP]["open_clip_model.safetensors"]), buf)
    files["open_clip_pytorch_model.bin"] = buf.getvalue()
    with HubServer() as hub:
        hub.add(HubRepo(get_spec(CLIP).repo_id, files))
        r = rg("models", "fetch", CLIP, "--json", env=online(hub, tmp_path))
    assert r.returncode == 0, r.stderr
    assert set(json.loads(r.stdout)[CLIP]["files"]) == {"open_clip_config.json", "open_clip_pytorch_model.bin", "tokenizer.json"}
    r = rg("models", "export", CLIP, "--json", env=offline(tmp_path))  # loads the .bin (torch.load, weights only)
    assert r.returncode == 0 and json.loads(r.stdout)[CLIP]["dim"] == 24, r.stderr


def test_offline_with_empty_cache_names_the_command(tmp_path):
    r = rg("models", "fetch", SAM, "--json", env=offline(tmp_path))
    assert r.returncode == 2
    err = json.loads(r.stdout)["error"]
    assert f"rg models fetch {SAM}" in err and "HF_HUB_OFFLINE" in err and str(tmp_path) in err, err
    # Using a preset whose models are absent fails before any mapping, naming fetch and export.
    r = rg("map", str(tmp_path / "no_scene"), "--out", str(tmp_path / "m.rgmap"), "--supervise", "--preset", "paper",
           "--json", env=offline(tmp_path))
    err = json.loads(r.stdout)["error"]
    assert r.returncode == 2 and f"rg models fetch {SAM}" in err and f"rg models export {SAM}" in err, err
    # Files placed by hand (no fetch manifest) are accepted offline and hashed.
    d = tmp_path / "slimsam-77"
    d.mkdir()
    for f in ("config.json", "model.safetensors", "preprocessor_config.json"):
        (d / f).write_bytes(f.encode())
    r = rg("models", "fetch", "slimsam-77", "--json", env=offline(tmp_path))
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["slimsam-77"]["files"]["config.json"]["sha256"] == hashlib.sha256(b"config.json").hexdigest()
    r = rg("models", "fetch", "no-such-model", "--json", env=offline(tmp_path))
    assert r.returncode == 2 and "unknown model 'no-such-model'" in json.loads(r.stdout)["error"]


def test_openclip_layout_round_trip():
    """OpenCLIP <-> transformers conversion is exact and keeps every tensor (fused q/k/v, transposed projections)."""
    from transformers import CLIPModel

    oc = {"model_cfg": {"embed_dim": 8, "vision_cfg": {"image_size": 16, "layers": 1, "width": 16, "patch_size": 8,
                                                        "head_width": 8},
                        "text_cfg": {"context_length": 5, "vocab_size": 11, "width": 16, "heads": 2, "layers": 1}}}
    cfg = hf_config(oc)
    assert cfg.vision_config.num_attention_heads == 2 and cfg.text_config.eos_token_id == 10
    torch.manual_seed(0)
    sd = {k: v for k, v in CLIPModel(cfg).state_dict().items() if not k.endswith("position_ids")}
    oc_sd = hf_to_openclip(sd, cfg)
    assert oc_sd["visual.transformer.resblocks.0.attn.in_proj_weight"].shape == (48, 16)
    assert oc_sd["visual.proj"].shape == (16, 8) and oc_sd["text_projection"].shape == (16, 8)
    back = openclip_to_hf(oc_sd, cfg)
    assert set(back) == set(sd) and all(torch.equal(back[k], sd[k]) for k in sd)
    with pytest.raises(ModelError, match="not a CLIP ViT config"):
        hf_config({"model_cfg": {"embed_dim": 8}})
    with pytest.raises(ModelError, match="hf_model_name"):
        hf_config({"model_cfg": {**oc["model_cfg"], "text_cfg": {**oc["model_cfg"]["text_cfg"], "hf_model_name": "x"}}})


def test_hub_server_serves_snapshot_download(tmp_path):
    """The loopback server is hub-shaped beyond what `rg models fetch` uses: huggingface_hub's
    snapshot_download (revision API, tree listing, resolve + LFS redirect) gets every file intact."""
    files = {"config.json": b'{"a": 1}', "model.safetensors": bytes(range(256)) * 40, "README.md": b"hi\n"}
    with HubServer() as hub:
        hub.add(HubRepo("facebook/sam-vit-huge", files))
        code = ("import sys; from huggingface_hub import snapshot_download; "
                "print(snapshot_download('facebook/sam-vit-huge', local_dir=sys.argv[1], endpoint=sys.argv[2]))")
        r = subprocess.run([sys.executable, "-c", code, str(tmp_path), hub.url], capture_output=True, text=True,
                           env={**os.environ, "HF_HUB_OFFLINE": "0"}, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert {f: (tmp_path / f).read_bytes() for f in files} == files
    assert any(p.startswith("/api/models/facebook/sam-vit-huge/tree/") for _, p, _ in hub.log)

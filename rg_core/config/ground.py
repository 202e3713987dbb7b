"""Section of grounding queries to Gaussian groups (rg_core/grounding)."""
from __future__ import annotations

from dataclasses import field
from typing import Annotated

from annotated_types import Interval

from .constants import MAX_QUERY_CHARS
from .schema import section


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
    this many map spacings (median nearest-neighbour distance, at least the median largest Gaussian
    axis: Grounder.spacing), and at least a photo map's depth resolution (Grounder.link_length); 0
    keeps the whole feature cluster."""
    anchor_support: bool = True
    """... and of those pieces the one with the most Gaussians the reference view sees inside its mask
    (else the most relevant point's piece): one pixel's depth can lie at a thin object's rim."""
    min_confidence: Annotated[float, Interval(ge=-1.0, le=1.0)] = -1.0
    """Answers less likely right than this are returned unsuccessful, with the best guess (abstain);
    -1 = the threshold fitted with the preset's confidence model, 0 = never abstain."""
    max_query_chars: Annotated[int, Interval(ge=1, le=1_000_000)] = MAX_QUERY_CHARS
    """Longer queries are rejected."""
    seed: int = 0

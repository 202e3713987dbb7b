"""Section of incremental Gaussian mapping (`rg map`, the node's map)."""
from __future__ import annotations

from typing import Annotated

from annotated_types import Interval

from .schema import section


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
class PhotoMapConfig:
    """Maps from posed photos without depth (issue 63): standard 3D Gaussian Splatting optimisation
    (Kerbl et al. 2023) with the project's rasterizer (rg_core/map/photo_fit.py). Iterations are
    counted, not seconds, so a seed stops at the same step on any CPU."""

    iters: Annotated[int, Interval(ge=1)] = 7000
    """Hard ceiling on optimisation steps (one view per step)."""
    steps_per_view: Annotated[int, Interval(ge=0)] = 35
    """The fit's ceiling is min(iters, max(min_iters, steps_per_view x views)) (0: iters alone), so a
    capture's time grows with its views: 100 views at 320x240 are queryable within 15 min on 2 cores
    (docs/benchmarks.md, bench_photo). The held-out test may end it earlier."""
    min_iters: Annotated[int, Interval(ge=1)] = 1000
    """Least ceiling of a small capture (17 views: 59 steps a view)."""
    lambda_dssim: Annotated[float, Interval(ge=0.0, le=1.0)] = 0.2
    """Loss = (1 - lambda) L1 + lambda (1 - SSIM), 3DGS's weighting."""
    depth_smoothness: Annotated[float, Interval(ge=0.0)] = 0.0
    """Weight of the edge-aware smoothness of the rendered depth (map/photo_losses.depth_smoothness):
    captures with little parallax leave depth free along the rays."""
    init_random: Annotated[int, Interval(ge=1)] = 5000
    """Gaussians drawn at random in the cameras' view volume when the scene has no sparse points."""
    triangulate: bool = True
    """A scene with poses but no sparse points gets them triangulated at its poses (pycolmap's SIFT
    matches, io/sfm.triangulate_posed) before falling back to random points."""
    triangulate_min_angle: Annotated[float, Interval(gt=0.0)] = 0.25
    """Least triangulation angle (degrees) of those points: known poses allow less than COLMAP's
    1.5 (cameras a few mm apart at a metre still give depth within ~20 %)."""
    densify_from: Annotated[int, Interval(ge=0)] = 100
    densify_until: Annotated[float, Interval(ge=0.0, le=1.0)] = 0.5
    """Adaptive density control runs from step densify_from to this share of `iters` (from 100, so a
    short fit densifies often enough to resolve a table top)."""
    densify_every: Annotated[int, Interval(ge=1)] = 100
    grad_threshold: Annotated[float, Interval(gt=0.0)] = 0.0001
    """Mean view-space positional gradient (NDC units, as 3DGS) above which a Gaussian is cloned
    (small) or split (large). Half 3DGS's 0.0002: fits of a few thousand steps densify less often
    than 3DGS's 30k, and the rendered depth feeds the physical scales (docs/pipeline.md)."""
    dense_share: Annotated[float, Interval(gt=0.0, lt=1.0)] = 0.01
    """Small / large: largest axis below / above this share of the scene extent."""
    prune_opacity: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.005
    prune_extent_share: Annotated[float, Interval(gt=0.0)] = 0.1
    """After the first opacity reset, Gaussians larger than this share of the extent go too."""
    reset_opacity_every: Annotated[int, Interval(ge=0)] = 3000
    """Opacities are clamped to 0.01 every this many steps while densifying (0 = never)."""
    holdout_views: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.1
    """Share of the views held out whole for the stop test (evenly spaced, at least one of 3 or
    more; 0: no stop test, all `iters` run); they are trained on after the stop is decided."""
    join_share: Annotated[float, Interval(ge=0.0, lt=1.0)] = 0.15
    """Steps after the decision, as a share of the fit: the held-out views join the training (the
    decision falls at the latest at (1 - join_share) x iters)."""
    check_every: Annotated[int, Interval(ge=1)] = 200
    converge_db: Annotated[float, Interval(ge=0.0)] = 0.05
    """Converged once the best held-out PSNR gained less than this (dB) over the last
    `converge_window` steps, after densification ended (0: run all `iters`)."""
    converge_window: Annotated[int, Interval(ge=1)] = 600
    lr_means: float = 0.00016
    """x the scene extent, decayed exponentially to 1 % over `iters` (3DGS)."""
    lr_scales: float = 0.005
    lr_quats: float = 0.001
    lr_opacity: float = 0.05
    lr_colors: float = 0.0025
    seed: int = 0
    world_scale: Annotated[float, Interval(ge=0.0)] = 0.0
    """COLMAP, LLFF and nerfstudio worlds without depth are defined only up to scale: on read their
    poses, points and bounds are multiplied by this factor (0: auto, so that the scene's typical
    viewing distance becomes `world_depth`; rg_core/io/world_scale.py). Scenes with depth keep theirs."""
    world_depth: Annotated[float, Interval(gt=0.0)] = 0.6
    """Metres the auto rule brings the median viewing distance to (the sparse points' median depth in
    the views, else LLFF's bounds, else the cameras' spread): what the mapper's and grounder's
    defaults suit (objects seen from 0.4-0.7 m)."""

"""The depth core's configuration: ELAS, the measurement model, the temporal filter and the
planar densification (the depth node's own parameters are nodes.depth_node.DepthNodeConfig;
config/depth.yaml overrides both). Every default lives here and nowhere else.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..config import Config, ConfigError

__all__ = ["DepthConfig", "ElasConfig"]


@dataclass
class ElasConfig(Config):
    """libelas: a preset (the parameter tables in depth.elas_matcher.ELAS_PRESETS), then these."""
    preset: str = "robotics"        # robotics (small gaps filled, fast) or middlebury (all gaps: denser, more wrong)
    disp_min: int = 0               # px, smallest disparity searched
    disp_max: int = 128             # px, largest disparity searched: Z >= f*B/disp_max; time grows with it
    subsampling: bool = True        # match every 2nd pixel, ~2-3x faster (stride 2 reads only those)

    def __post_init__(self):
        super().__post_init__()
        self.preset = self.preset.strip().lower()
        if self.preset not in ("robotics", "middlebury"):
            raise ConfigError("ElasConfig.preset must be robotics or middlebury, got %r" % self.preset)
        if not 0 <= self.disp_min < self.disp_max:
            raise ConfigError("ElasConfig wants 0 <= disp_min < disp_max, got %d and %d"
                              % (self.disp_min, self.disp_max))


@dataclass
class DepthConfig(Config):
    """StereoDepth's parameters: weak-texture matching, measurement model, keyframe Kalman filter,
    planar densification and ``elas`` (see depth.stereo_depth, depth.filter, depth.densify)."""
    # --- measurement model: Z = f*B/d, sigma_Z = Z^2 * sigma_d / (f*B)
    sigma_d: float = 0.5            # px, disparity noise of an ELAS match on texture
    sigma_d_texture: float = 1.0    # k: adds (k / local x-gradient)^2 px^2 on low texture; 0: constant sigma_d
    # --- weak texture: where the image has too little texture, OpenCV's semi-global matcher instead
    # of ELAS (ELAS' weak-texture disparities carry a bias that repeats from frame to frame, so the
    # filter never converges there; SGBM's errors there are unbiased: depth/weak_texture.py)
    weak_texture: str = "sgbm"      # sgbm: SGBM on weak-texture pixels (temporal filter only); off: ELAS everywhere (the paper)
    weak_texture_gradient: float = 3.0  # grey levels/px: RMS x-gradient over 5x5 below which a pixel is weak texture
    max_disparity_step: float = 3.0  # px: drop pixels near a larger disparity step (flying pixels); 0: keep all
    discontinuity_radius: int = 2   # px, half size of that test's window ((2r+1)^2; 0: nothing dropped)
    min_depth: float = 0.2          # m, nearer measurements are dropped
    max_depth: float = 8.0          # m, farther measurements are dropped (a px of disparity is metres there)
    # --- temporal filter (state: inverse depth per keyframe pixel)
    temporal: bool = True           # false: the paper's ELAS-only baseline (every valid pixel, every frame)
    stride: int = 2                 # px, state on every stride-th pixel in x and y (2: ~4x faster); >= 1
    kf_translation: float = 0.30    # m moved since the keyframe: new keyframe
    kf_rotation_deg: float = 15.0   # deg turned since the keyframe: new keyframe
    kf_min_overlap: float = 0.60    # new keyframe when fewer of its points are in view (0: never)
    kf_max_frames: int = 30         # frames per keyframe at most (unless the pose node's keyframes rule)
    init_var_scale: float = 4.0     # keyframe init: ELAS variance times this (high initial uncertainty)
    chi2_threshold: float = 6.63    # gate on innovation^2 / (P + R): chi-square, 1 dof, 99 %
    process_noise: float = 0.003    # relative depth std added per frame, keeps the filter responsive; 0: none
    reinit_min_rejections: int = 3  # restart a pixel gated at least this often ...
    reinit_ratio: float = 2.0       # ... and more than this many times as often as accepted
    fill_holes: bool = True         # start hypotheses in keyframe holes from later frames
    motion_stereo: bool = False     # also match new keyframes' unconverged pixels in earlier keyframes (wider baselines: far walls)
    tau: float = 0.01               # publish when sigma_Z / Z <= tau: lower, fewer and more accurate points
    min_obs: int = 3                # ... and at least this many fused observations (init included)
    carry_over: bool = True         # carry well-observed points into the next keyframe
    carry_tau: float = 0.03         # ... those with sigma_Z / Z <= carry_tau and min_obs observations
    publish_visible_only: bool = True  # publish only converged points in the current view
    # --- planar densification (depth/densify.py): planes fitted on converged points fill low texture
    densify: str = "off"            # plane: publish plane fills of non-converged pixels (n_obs 0); off
    densify_min_support: int = 60   # converged inliers a new plane needs
    densify_max_dist: int = 40      # grid cells: fill at most this far from the plane's support; 0: no limit
    densify_memory: int = 30        # planes remembered (map frame) to fill later keyframes; 0: none
    densify_prior_margin: float = 0.5  # m around the map box a remembered plane filled with support
    densify_max_incidence_deg: float = 75.0  # deg: no fill where the ray meets the plane more obliquely
    densify_max_depth: float = 0.0  # m, fill only nearer than this; 0: max_depth
    densify_every: int = 5          # frames of a keyframe between two plane fits
    densify_min_obs: int = 3        # a hypothesis takes part with this many observations ...
    densify_max_rel: float = 0.15   # ... and sigma_rho / rho <= this
    densify_chi2: float = 6.63      # a pixel agrees with a plane: residual^2 <= chi2 * its variance ...
    densify_max_dev: float = 0.04   # ... and (to build regions) |residual| <= this * rho
    densify_min_pixels: int = 300   # grid cells of agreeing pixels one connected region needs
    densify_max_planes: int = 10    # planes per keyframe
    densify_hypotheses: int = 96    # RANSAC hypotheses per plane
    densify_patch: int = 9          # grid cells, half size of a hypothesis' patch
    densify_close: int = 2          # grid cells, morphological closing of a plane's inlier mask
    densify_min_density: float = 0.6  # share of a region's cells that must be inliers
    densify_max_hole: int = 400     # grid cells: enclosed holes up to this size are filled; 0: none
    densify_max_rchi2: float = 3.0  # refuse a plane whose inliers scatter more than this x their variance
    densify_var_floor: float = 0.01  # relative sigma floor of a filled depth (sigma_Z / Z)
    # --- libelas
    elas: ElasConfig = field(default_factory=ElasConfig)

    def __post_init__(self):
        super().__post_init__()
        if self.stride < 1:
            raise ConfigError("DepthConfig.stride must be >= 1, got %d" % self.stride)
        if self.weak_texture not in ("off", "sgbm"):
            raise ConfigError("DepthConfig.weak_texture must be sgbm or off (quoted in YAML, where "
                              "a bare off is false), got %r" % (self.weak_texture,))
        if self.densify not in ("off", "plane"):
            raise ConfigError("DepthConfig.densify must be plane or off (quoted in YAML, where a "
                              "bare off is false), got %r" % (self.densify,))


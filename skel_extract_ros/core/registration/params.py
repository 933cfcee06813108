"""Parameters and per-frame results of the non-rigid registration (Alg. 1)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..parameters import INF, parameter, validate

STATUS_OK = 'ok'
STATUS_EMPTY = 'empty'
STATUS_DIVERGED = 'diverged'
M_STEPS = ('translations_rotations', 'per_node')
SMOOTHNESS = ('robust', 'paper')


@dataclass
class RegistrationParams:
    """Parameters of the registration (defaults: the paper's Table 1 where it gives one).
    smoothness 'robust' is described in the module docstring ("Robust smoothness");
    e_step_neighbours >= M with truncation_sigmas = inf is exact EM."""

    omega: float = parameter(0.01, 'weight of the uniform outlier component of the GMM (Eq. 1, 3), '
                             'a probability', 0.0, 0.999)
    smoothness: str = parameter('robust', 'deformation graph smoothness: robust (weight relative to sigma2, '
                                'Geman-McClure loss per edge, so a limb can leave the body it touched in the '
                                'first frame) or paper (Eq. 4 as written, fixed beta_smooth)', choices=SMOOTHNESS)
    beta_smooth: float = parameter(1e5, 'weight of E_smooth with smoothness paper (Eq. 4, Table 1), 1/m^2',
                                   0.0, INF)
    beta_smooth_relative: float = parameter(4.0, 'with smoothness robust, E_smooth is weighted this / sigma2 '
                                            '(the units of the data term), dimensionless', 0.0, INF)
    edge_strain_scale: float = parameter(0.5, 'with smoothness robust, the Geman-McClure scale of an edge: a '
                                         'residual this fraction of the edge length (about the relative '
                                         'rotation of its nodes, rad) weighs a quarter', 1e-6, 100.0)
    beta_small: float = parameter(1.0, 'weight of E_small, the small-motion term between frames (Eq. 4), '
                                  'dimensionless', 0.0, INF)
    visibility: bool = parameter(False, 'model points hidden behind the observed surface (farther than the '
                                 "E-step's reach) take no observations in that frame and follow the graph; "
                                 'false = every point may claim observations (the paper)')
    free_space: float = parameter(0.0, 'weight of the silhouette term: a registered point outside the observed '
                                  "silhouette, within the E-step's reach of it, is pulled onto the nearest observed "
                                  'ray at its own range, weighted this x the median posterior mass of the points '
                                  'with data; 0 = off (the paper), dimensionless', 0.0, INF)
    inertia: float = parameter(0.75, "each frame's EM starts from the last registered points moved on along their "
                               'last step by this x the step their last two steps agree on (none on a reversal, '
                               'less when slowing; scaled to the time between frames when stamps are given; each '
                               "point at most the E-step's reach at initial_sigma2); 0 = from the last "
                               'registered pose (the paper), dimensionless', 0.0, 1.0)
    extremity_weight: float = parameter(3.0, "weight of the extremity landmarks: each frame the geodesic "
                                        "extremities of the observed points (the limbs' ends, core.extremities) "
                                        "are matched to the rest points' own, and each matched end of the model is "
                                        "pulled onto its partner, weighted this x the median posterior mass of the "
                                        "points with data; 0 = off (the paper), dimensionless", 0.0, INF)
    recapture: bool = parameter(True, 'after EM, move a part left without data rigidly onto the observations '
                                'nothing explains and re-run EM (fast limbs)')
    initial_sigma2: float = parameter(6e-4, 'GMM variance at the start of every frame, m^2 (Sec. 7)', 1e-12, INF)
    max_iterations: int = parameter(20, 'EM iterations per frame at most (Alg. 1)', 1, 1000)
    tolerance: float = parameter(1e-3, 'stop EM when the relative energy change is below this, dimensionless',
                                 0.0, 1.0)
    m_step: str = parameter('translations_rotations', 'M-step scheme: translations_rotations (converges with '
                            "stiff beta_smooth) or per_node (the paper's node-by-node scheme; needs smoothness "
                            'paper)', choices=M_STEPS)
    node_spacing: float | None = parameter(None, 'deformation graph node spacing, m; 0 = automatic '
                                           '(node_spacing_factor)', 0.0, INF)
    node_spacing_factor: float = parameter(3.5, 'automatic node spacing = this x the median rest point spacing '
                                           '(so the graph is equally fine on a hand and a body), dimensionless',
                                           1.0, 100.0)
    n_influence: int = parameter(4, 'deformation graph nodes blending each point (k in Eq. 2)', 1, 16)
    e_step_neighbours: int = parameter(8, 'truncated E-step: nearest centroids per observed point (at least M '
                                       'with truncation_sigmas inf: exact EM)', 1, 1_000_000)
    truncation_sigmas: float = parameter(4.0, 'truncated E-step: neighbour radius in GMM standard deviations',
                                         1.0, INF)
    mass_cap: float = parameter(0.0, 'balanced E-step: a model point whose posterior mass passes this many '
                                'times the median of the model points with data has its share scaled down '
                                '(three passes), so the observations beyond a limb that slid back along itself '
                                'pull its end as a whole, not its last point alone; 0 = Eq. 3 as written (the '
                                'default), else at least 1', 0.0, INF)
    min_sigma2: float = parameter(1e-6, 'lower bound of the GMM variance (a perfect fit cannot collapse the '
                                  'Gaussians), m^2', above=0.0, high=INF)
    max_sigma2: float = parameter(1e-2, 'a frame whose variance ends above this has diverged (the last good '
                                  'state is kept), m^2', above=0.0, high=INF)
    min_matched_fraction: float = parameter(0.3, 'a frame whose observations the GMM explains for less than '
                                            'this share of their mass has diverged, a fraction', 0.0, 1.0)
    min_points: int = parameter(50, 'a preprocessed frame with fewer points is skipped as empty, points',
                                1, 10_000_000)
    coarse_to_fine: bool = parameter(False, 'each frame, EM also runs from the result of a first pass on a '
                                     'coarser graph whose E-step reaches as far as the fastest node moved in the '
                                     'last registered frame; the frame keeps the run with the lower objective at '
                                     'initial_sigma2 (a prototype: off)')
    coarse_spacing_factor: float = parameter(2.0, 'with coarse_to_fine, node spacing of the coarse graph = this x '
                                             "the graph's, dimensionless", 1.0, 100.0)

    def __post_init__(self):
        validate(self)
        if 0.0 < self.mass_cap < 1.0:
            raise ValueError(f'mass_cap must be 0 (off) or at least 1 (the median itself), got {self.mass_cap}')
        if self.m_step == 'per_node' and self.smoothness != 'paper':
            raise ValueError("m_step 'per_node' is the paper's scheme and needs smoothness 'paper'")


@dataclass
class FrameResult:
    """Outcome of registering one frame.

    points: (M, 3) registered points y' (the last good ones if the frame failed), metres.
    sigma2: final variance (m^2); energies: objective after each E-step.
    matched_fraction: N_p / N, the share of the observations the GMM explains.
    recaptured: parts moved back onto their observations in this frame (`recapture`).
    landmarks: the model's limb ends matched to the frame's and pulled onto them
    (`extremity_weight`).
    """

    points: np.ndarray
    status: str
    sigma2: float
    iterations: int
    matched_fraction: float
    energies: list = field(default_factory=list)
    recaptured: int = 0
    landmarks: int = 0

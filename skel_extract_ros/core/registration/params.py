"""Parameters and per-frame results of the non-rigid registration (Alg. 1)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

STATUS_OK = 'ok'
STATUS_EMPTY = 'empty'
STATUS_DIVERGED = 'diverged'
M_STEPS = ('translations_rotations', 'per_node')
SMOOTHNESS = ('robust', 'paper')


@dataclass
class RegistrationParams:
    """Parameters of the registration (defaults: the paper's Table 1 where it gives one).

    omega: weight of the uniform outlier component (Eq. 1).
    smoothness: 'robust' (default) or 'paper'. 'paper' is Eq. (4) as written: E_smooth
        quadratic with the fixed weight beta_smooth. 'robust' (see "Robust smoothness" in
        the module docstring) weighs E_smooth by beta_smooth_relative / sigma2 and gives
        every graph edge a Geman-McClure loss with scale edge_strain_scale.
    beta_smooth: weight of E_smooth with smoothness='paper' (1 / m^2, Table 1).
    beta_smooth_relative: with smoothness='robust', E_smooth is weighted
        beta_smooth_relative / sigma2, in the units of the data term.
    edge_strain_scale: with smoothness='robust', the Geman-McClure scale of an edge's
        residual as a fraction of its rest length (about the relative rotation of its
        two nodes, radians) at which the edge weighs a quarter.
    beta_small: weight of E_small (Eq. 4).
    visibility: model points the camera cannot see in a frame (behind an observed surface
        by more than the E-step's reach) take no part in that frame's E-step and follow
        the graph (`ObservedView`). False: every point may claim observations (the paper).
    recapture: after EM, a part left without data is moved rigidly onto the observations
        nothing explains, and EM re-run from there (`core.recapture`).
    initial_sigma2: GMM variance at the start of every frame, m^2 (Sec. 7).
    max_iterations, tolerance: EM stops after max_iterations or when the relative energy
        change falls below tolerance (Sec. 6, last paragraph).
    m_step: 'translations_rotations' (default) or 'per_node' (the paper's scheme); see the
        module docstring.
    node_spacing: deformation-graph node spacing in metres; None picks
        `node_spacing_factor` times the median spacing of the rest points, so the graph is
        equally fine on a hand and on a body.
    n_influence: nodes carrying each point (k in Eq. 2).
    e_step_neighbours, truncation_sigmas: the truncated E-step (each observation sees at
        most this many centroids, within this many sigmas); e_step_neighbours >= M with
        truncation_sigmas = inf is exact EM.
    min_sigma2: floor on sigma2 (m^2), so a perfect fit cannot collapse the Gaussians.
    max_sigma2, min_matched_fraction: a frame whose sigma2 ends above max_sigma2, or whose
        observations are explained by the GMM for less than this fraction of their mass,
        has diverged: the last good state is kept.
    min_points: fewer observed points than this is an empty frame.
    """

    omega: float = 0.01
    smoothness: str = 'robust'
    beta_smooth: float = 1e5
    beta_smooth_relative: float = 4.0
    edge_strain_scale: float = 0.5
    beta_small: float = 1.0
    visibility: bool = False
    recapture: bool = True
    initial_sigma2: float = 6e-4
    max_iterations: int = 20
    tolerance: float = 1e-3
    m_step: str = 'translations_rotations'
    node_spacing: float | None = None
    node_spacing_factor: float = 3.5
    n_influence: int = 4
    e_step_neighbours: int = 8
    truncation_sigmas: float = 4.0
    min_sigma2: float = 1e-6
    max_sigma2: float = 1e-2
    min_matched_fraction: float = 0.3
    min_points: int = 50

    def __post_init__(self):
        if not 0.0 <= self.omega < 1.0:
            raise ValueError(f'omega must be in [0, 1), got {self.omega}')
        for name in ('beta_smooth', 'beta_small', 'beta_smooth_relative'):
            if getattr(self, name) < 0:
                raise ValueError(f'{name} must be non-negative')
        for name in ('initial_sigma2', 'min_sigma2', 'max_sigma2', 'truncation_sigmas', 'node_spacing_factor',
                     'edge_strain_scale'):
            if getattr(self, name) <= 0:
                raise ValueError(f'{name} must be positive')
        if self.max_iterations < 1 or self.e_step_neighbours < 1 or self.n_influence < 1:
            raise ValueError('max_iterations, e_step_neighbours and n_influence must be >= 1')
        if self.m_step not in M_STEPS:
            raise ValueError(f'm_step must be one of {M_STEPS}, got {self.m_step!r}')
        if self.smoothness not in SMOOTHNESS:
            raise ValueError(f'smoothness must be one of {SMOOTHNESS}, got {self.smoothness!r}')
        if self.m_step == 'per_node' and self.smoothness != 'paper':
            raise ValueError("m_step 'per_node' is the paper's scheme and needs smoothness 'paper'")


@dataclass
class FrameResult:
    """Outcome of registering one frame.

    points: (M, 3) registered points y' (the last good ones if the frame failed), metres.
    sigma2: final variance (m^2); energies: objective after each E-step.
    matched_fraction: N_p / N, the share of the observations the GMM explains.
    recaptured: parts moved back onto their observations in this frame (`recapture`).
    """

    points: np.ndarray
    status: str
    sigma2: float
    iterations: int
    matched_fraction: float
    energies: list = field(default_factory=list)
    recaptured: int = 0

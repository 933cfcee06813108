r"""Non-rigid GMM registration with an embedded deformation graph (paper Sec. 4, Alg. 1).

Model. The observed points V (N, 3) of a frame are drawn from a GMM whose M centroids are
the deformed rest points y'_m (Eq. 2), with one isotropic variance sigma2 and a uniform
outlier component of weight omega (Eq. 1). EM alternates:

E-step (Eq. 3), truncated: p_mi = exp(-|v_i - y'_m|^2 / 2 sigma2) / (sum_m' ... + c),
    c = (2 pi sigma2)^{3/2} omega M / ((1 - omega) N).
    Only pairs within `truncation_sigmas` * sigma of each other, at most
    `e_step_neighbours` centroids per observation (its nearest: a k-d tree over the
    centroids, `core.gmm`), are kept: a Gaussian beyond 3 sigma weighs < 1.1 % of its
    peak, and the dense N x M matrix is never formed (memory O(N k), not O(N M)). The
    neighbour lists are queried again only when a centroid has moved a rest spacing or
    sigma has grown (`core.gmm.CandidateCache`, as in Alg. 2 and the live fit): once EM
    has found the frame the centroids move by millimetres, and the query is a large part
    of an iteration. With `mass_cap` > 0 (off by default) a centroid far over the
    median posterior mass hands part of it to its neighbours (`core.gmm`, "Balanced
    E-step"): no longer Eq. 3's E-step, so the convergence statement below is for
    mass_cap 0.

M-step (Eq. 4): E_GMM + beta_smooth / 2 E_smooth + beta_small / 2 E_small over the node
transforms, R_j in SO(3), in exact blocks that never raise it (`m_step`, with the
derivation of Eq. 5 and 6); E_smooth robust or quadratic (`graph_terms`).

sigma2 (Eq. 7): sigma2 = sum_mi p_mi |v_i - y'_m|^2 / (3 N_p), with the new y'.

Recapture (`recapture=True`, core/recapture.py): after EM, a part with no posterior mass
and a group of observations beyond every centroid's reach are matched, the part is moved
rigidly onto them and EM is re-run from there; the result is kept if it explains more of the
frame (larger N_p).

Extremity landmarks (`extremity_weight` > 0, core/extremities.py): the data term cannot tell
where along a featureless limb the model sits, only the limb's end can, and Eq. 3 gives that
end a few observations among many. Each frame the geodesic extremities of the observed
points (the limbs' ends) are matched to the rest points' own (where the frame starts them),
and in every M-step each matched end of the model gets pseudo-observations that move it, as
a whole, onto its partner's centroid. The data's statistics (Eq. 7's sigma2, the energy,
what recapture reads) are left as they are: the landmarks only steer the M-step, so, as
with `free_space`, the statement below is for the objective without them.

Convergence: the quantity EM decreases is the negative log-likelihood of Eq. (1) plus
beta_smooth / 2 E_smooth (E_small vanishes at the previous iterate, so it acts as a
proximal term and cannot make the objective rise). `FrameResult.energies` reports exactly
that. With exact EM (all centroids, no radius) it never increases (tested). With the
truncated E-step it may rise late in a frame, for a precise reason: as sigma shrinks, an
observation that leaves every centroid's truncation ball loses its Gaussian term and counts
as an outlier only, so the truncated likelihood changes support between iterations; noise
with heavier tails than the Gaussian (depth quantisation, flying pixels) makes this happen.
The sigma2 floor (min_sigma2) can likewise stop the sigma2 step from being a full minimiser.


The module per part: `params` (RegistrationParams, FrameResult, the frame statuses),
`graph_terms` (the deformation graph's precomputed structures and E_smooth, robust or
quadratic), `m_step` (the exact blocks of the M-step, Eq. 4-6), `visibility` (which model
points the camera could have seen, and which lie outside the silhouette), `nonrigid`
(NonRigidRegistration: the EM loop of Alg. 1 over them, recapture, the landmarks;
`register_chains`: independent chains of frames at once).
"""
from .graph_terms import GraphTerms
from .m_step import GraphMStep
from .nonrigid import NonRigidRegistration, register_chains
from .params import M_STEPS, SMOOTHNESS, STATUS_DIVERGED, STATUS_EMPTY, STATUS_OK, FrameResult, RegistrationParams
from .visibility import ObservedView

__all__ = ['FrameResult', 'GraphMStep', 'GraphTerms', 'M_STEPS', 'NonRigidRegistration', 'ObservedView',
           'RegistrationParams', 'SMOOTHNESS', 'STATUS_DIVERGED', 'STATUS_EMPTY', 'STATUS_OK', 'register_chains']

"""NonRigidRegistration: the EM loop of Alg. 1 over the graph's terms and the M-step blocks,
frame by frame, with recapture of lost parts and unseen parts carried along."""
from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace

import numpy as np

from ..deformation_graph import DeformationGraph
from ..extremities import find_extremities, match_extremities
from ..gmm import CandidateCache, GMMStatistics, gmm_posteriors
from ..parallel import parallel_map
from ..point_sets import finite_rows, median_spacing, voxel_centroids
from ..recapture import find_recaptures, lost_parts
from ..rigid import fit_weighted_segments, weighted_rigid_fit
from .graph_terms import GraphTerms
from .m_step import GraphMStep
from .params import STATUS_DIVERGED, STATUS_EMPTY, STATUS_OK, FrameResult, RegistrationParams
from .visibility import ObservedView


@dataclass
class _EMState:
    """Node transforms, registered points (M, 3), sigma2 and the last E-step of one EM run."""

    rotations: np.ndarray
    translations: np.ndarray
    points: np.ndarray
    sigma2: float
    estep: GMMStatistics | None
    iterations: int
    energies: list
    recaptured: int = 0


class NonRigidRegistration(GraphTerms, GraphMStep):
    """Tracks a rest point set through a sequence, frame by frame (Alg. 1).

    >>> registration = NonRigidRegistration(rest_points, RegistrationParams())
    >>> result = registration.register_frame(observed_points)   # (N, 3) -> FrameResult

    State (node rotations and translations) carries over from frame to frame; a frame that
    is empty or diverges leaves it unchanged.
    """

    def __init__(self, rest_points: np.ndarray, params: RegistrationParams | None = None):
        self.params = params or RegistrationParams()
        rest_points = np.asarray(rest_points, dtype=np.float64)
        if rest_points.ndim != 2 or rest_points.shape[1] != 3 or len(rest_points) < 10:
            raise ValueError(f'rest points must be (M >= 10, 3), got {rest_points.shape}')
        # the rest points' spacing: a centroid that moved less has passed no other (CandidateCache)
        self.point_spacing = median_spacing(rest_points)
        spacing = self.params.node_spacing or self.params.node_spacing_factor * self.point_spacing
        self.node_spacing = spacing
        self.graph = DeformationGraph.build(rest_points, spacing, self.params.n_influence)
        n_nodes = self.graph.n_nodes
        self.rotations = np.tile(np.eye(3), (n_nodes, 1, 1))
        self.translations = np.zeros((n_nodes, 3))
        self.points = rest_points.copy()
        # inertia: the registered points of the two registered frames before the last (None
        # until there are) and the stamps (s) of the three, newest first, when the caller
        # gives them
        self._previous_points = None
        self._earlier_points = None
        self._stamps = (None, None, None)
        self._prepare()
        # extremity landmarks: the rest points' own limb ends, and this frame's matched pairs
        # (model region indices, observed centroid (3,) m)
        self._extremities = None
        self._landmarks = []
        if self.params.extremity_weight > 0:
            self._centre = int(np.argmin(np.linalg.norm(rest_points - rest_points.mean(axis=0), axis=1)))
            self._extremities = find_extremities(rest_points, self._centre)
        # coarse_to_fine: the coarser graph of the first pass, and how far the fastest node
        # moved in the last registered frame (m; 0 before there is one)
        self._coarse = None
        self.last_step_ = 0.0
        self.coarse_chosen_ = 0     # frames whose result came from the coarse start
        if self.params.coarse_to_fine:
            coarse = replace(self.params, coarse_to_fine=False, recapture=False, inertia=0.0, extremity_weight=0.0,
                             node_spacing=self.params.coarse_spacing_factor * spacing)
            self._coarse = NonRigidRegistration(rest_points, coarse)

    @property
    def rest_points(self) -> np.ndarray:
        return self.graph.rest_points

    def reset(self) -> None:
        """Back to the rest pose (identity node transforms)."""
        self.rotations[:] = np.eye(3)
        self.translations[:] = 0.0
        self.points = self.rest_points.copy()
        self._previous_points = None
        self._earlier_points = None
        self._stamps = (None, None, None)
        self._landmarks = []
        self.last_step_ = 0.0

    # ----------------------------------------------------------------------------------
    def _e_step(self, observed: np.ndarray, points: np.ndarray, sigma2: float,
                view: 'ObservedView | None' = None, cache: CandidateCache | None = None) -> GMMStatistics:
        """Eq. (3), balanced by mass_cap (gmm module docstring), over the centroids the camera
        can see (`visibility`; all without it); without it, over the candidates of `cache`
        (the frame's CandidateCache)."""
        p = self.params
        if view is None or not p.visibility:
            if cache is not None:
                return cache.posteriors(points, sigma2, p.omega, p.truncation_sigmas, p.mass_cap)
            return gmm_posteriors(observed, points, sigma2, p.omega, p.e_step_neighbours, p.truncation_sigmas,
                                  mass_cap=p.mass_cap)
        visible = view.visible(points, p.truncation_sigmas * np.sqrt(sigma2))
        self.last_visible_ = visible
        stats = gmm_posteriors(observed, points[visible], sigma2, p.omega, p.e_step_neighbours,
                               p.truncation_sigmas, mass_cap=p.mass_cap)
        P1 = np.zeros(len(points))
        Px = np.zeros((len(points), 3))
        P1[visible], Px[visible] = stats.P1, stats.Px
        return GMMStatistics(P1, Px, stats.Np, stats.nll, stats.weighted_sq)

    def _with_silhouette(self, estep: GMMStatistics, points: np.ndarray, view: 'ObservedView',
                         sigma2: float) -> GMMStatistics:
        """The statistics the M-step fits with the silhouette term (`free_space`): each point
        (M, 3) m that the observed silhouette does not cover, within the E-step's reach of it,
        gets a pseudo-observation on the nearest observed ray at its own range, of weight
        free_space x the median posterior mass of the points with data. The E-step pulls a
        point only towards observations; this also pushes it out of where the camera saw
        nothing. Eq. 7's sigma2, the energy, and the support that recapture and the carry of
        unseen parts read keep the real data's statistics."""
        outside, targets = view.silhouette_targets(points, self.params.truncation_sigmas * np.sqrt(sigma2))
        # the points with data: a thousandth of an observation's mass or more
        with_data = estep.P1 > 1e-3
        if not outside.any() or not with_data.any():
            return estep
        weight = self.params.free_space * float(np.median(estep.P1[with_data])) * outside
        P1 = estep.P1 + weight
        return GMMStatistics(P1, estep.Px + weight[:, None] * targets, float(P1.sum()), estep.nll,
                             estep.weighted_sq)

    def _match_landmarks(self, observed: np.ndarray, start_points: np.ndarray) -> list:
        """This frame's extremity landmarks: the geodesic extremities of the observed points
        (N, 3) m, sampled at the rest points' spacing (their voxel centroids), from the
        sample nearest where the frame starts the rest points' centre, matched to the model's
        ends where the frame starts them (start_points (M, 3) m;
        core.extremities.match_extremities). The reach of a model end: the E-step's reach
        at initial_sigma2, plus as far as the end moved in the last registered frame, up to
        as much again (a fast limb's start is further off; a lost one must not widen its own
        reach frame after frame). -> [(model region indices, observed end's centroid (3,) m)]."""
        model = self._extremities
        # the ends need the surface's shape, not every observation, and their graph's cost
        # grows with the points: a subject nearer the camera than in its rest frame is
        # sampled more densely than the rest points
        sampled = voxel_centroids(observed, self.point_spacing)
        centre = int(np.argmin(np.linalg.norm(sampled - start_points[self._centre], axis=1)))
        found = find_extremities(sampled, centre)
        reach = np.full(len(model), self.params.truncation_sigmas * np.sqrt(self.params.initial_sigma2))
        if self._previous_points is not None:
            last_step = self.points - self._previous_points
            moved = np.array([np.linalg.norm(last_step[region].mean(axis=0)) for region in model.regions])
            reach += np.minimum(moved, reach)
        pairs = match_extremities(model, start_points, found, reach)
        return [(model.regions[k], found.centroids[l]) for k, l in pairs]

    def _with_landmarks(self, estep: GMMStatistics, points: np.ndarray) -> GMMStatistics:
        """The statistics the M-step fits with the extremity landmarks: each matched model end
        (its region of the points (M, 3) m) gets pseudo-observations that move it, as a whole,
        onto its observed partner's centroid, each of weight extremity_weight x the median
        posterior mass of the points with data. Eq. 7's sigma2 and the energy keep the real
        data's statistics."""
        with_data = estep.P1 > 1e-3
        if not with_data.any():
            return estep
        weight = self.params.extremity_weight * float(np.median(estep.P1[with_data]))
        P1, Px = estep.P1.copy(), estep.Px.copy()
        for region, target in self._landmarks:     # a few limb ends, not points
            shift = target - points[region].mean(axis=0)
            P1[region] += weight
            Px[region] += weight * (points[region] + shift)
        return GMMStatistics(P1, Px, float(P1.sum()), estep.nll, estep.weighted_sq)

    def _node_support(self, estep: GMMStatistics) -> np.ndarray:
        """(J,) posterior mass per carried point that each node's points received (0: no data)."""
        return (self._blend.T @ estep.P1) / self._node_mass

    def _run_em(self, observed: np.ndarray, view: 'ObservedView | None', rotations: np.ndarray,
                translations: np.ndarray, iterations_done: int = 0) -> '_EMState':
        """EM (Alg. 1) from the node transforms given, to convergence or max_iterations.
        view: the frame's ObservedView, for `visibility` and `free_space` (None: neither)."""
        p = self.params
        hiding = view is not None and p.visibility
        silhouette = view is not None and p.free_space > 0
        rotated = self._rotated_offsets(rotations)
        contributions = self._contributions(rotations, translations, rotated)
        points = contributions.sum(axis=1)
        sigma2 = p.initial_sigma2
        energies = []
        iterations = 0
        estep = None
        # the visible subset changes between iterations: its E-step queries every time
        cache = None if hiding else CandidateCache(observed, self.point_spacing, p.e_step_neighbours)
        for iterations in range(1, p.max_iterations + 1):
            estep = self._e_step(observed, points, sigma2, view, cache)
            # the objective and the IRLS weights below are both at these transforms
            residuals = self.edge_residuals(rotations, translations)
            energies.append(estep.nll + self.smoothness_penalty(rotations, translations, sigma2, residuals))
            if len(energies) > 1 and abs(energies[-2] - energies[-1]) <= p.tolerance * abs(energies[-1]):
                break
            if estep.Np <= 1e-9:
                break
            fitted = self._with_silhouette(estep, points, view, sigma2) if silhouette else estep
            if self._landmarks:
                fitted = self._with_landmarks(fitted, points)
            if p.m_step == 'translations_rotations':
                # IRLS: the robust edge weights are fixed at this iteration's transforms
                stiffness = self.edge_stiffness(rotations, translations, sigma2,
                                                self.last_visible_ if hiding else None, residuals)
                self._solve_translations(fitted, sigma2, rotations, translations, rotated, stiffness)
                contributions = self._contributions(rotations, translations, rotated)
                self._update_rotations(fitted, sigma2, contributions, rotations, translations, rotated, stiffness)
                rotated = self._rotated_offsets(rotations)
                contributions = self._contributions(rotations, translations, rotated)
            else:
                self._update_nodes(fitted, sigma2, contributions, rotations, translations)
            points = contributions.sum(axis=1)
            # Eq. (7): sum_mi p_mi |v_i - y'_m|^2 / (3 N_p)
            sigma2 = max(estep.squared_residual(points) / (3.0 * estep.Np), p.min_sigma2)
            if sigma2 > p.max_sigma2:
                break
        return _EMState(rotations, translations, points, sigma2, estep, iterations_done + iterations, energies)

    def _recapture(self, observed: np.ndarray, view: 'ObservedView | None', state: '_EMState') -> '_EMState':
        """Turn parts EM left behind onto the observations nothing explains (core.recapture),
        re-run EM from there, and keep that if it explains more of the frame."""
        p = self.params
        graph = self.graph
        if not np.isfinite(state.sigma2):
            return state
        support = self._node_support(state.estep)
        reach = p.truncation_sigmas * np.sqrt(state.sigma2)
        main_node = graph.point_nodes[np.arange(len(graph.rest_points)), np.argmax(graph.point_weights, axis=1)]
        node_positions = graph.node_positions + state.translations
        found = find_recaptures(observed, state.points, node_positions, support, graph.edges, main_node, reach)
        if not found:
            return state
        rotations, translations = state.rotations.copy(), state.translations.copy()
        for capture in found:
            nodes = capture.nodes
            rotations[nodes] = np.einsum('ij,njk->nik', capture.rotation, rotations[nodes])
            moved = node_positions[nodes] @ capture.rotation.T + capture.shift
            translations[nodes] = moved - graph.node_positions[nodes]
        retried = self._run_em(observed, view, rotations, translations, state.iterations)
        if retried.estep is None or not retried.estep.Np > state.estep.Np:
            return state
        retried.energies = state.energies + retried.energies
        retried.recaptured = len(found)
        return retried

    def _em_from(self, observed: np.ndarray, view: 'ObservedView | None', start: tuple) -> '_EMState':
        """EM (and recapture) from the node transforms `start` = (rotations, translations)."""
        state = self._run_em(observed, view, start[0].copy(), start[1].copy())
        if self.params.recapture and state.estep is not None:
            state = self._recapture(observed, view, state)
        return state

    def _frame_energy(self, observed: np.ndarray, state: '_EMState') -> float:
        """The objective of a frame's result at the common sigma2 initial_sigma2 (EM runs end
        at different sigma2, so their own energies do not compare)."""
        p = self.params
        stats = gmm_posteriors(observed, state.points, p.initial_sigma2, p.omega, p.e_step_neighbours,
                               p.truncation_sigmas)
        return stats.nll + self.smoothness_penalty(state.rotations, state.translations, p.initial_sigma2)

    def _coarse_start(self, observed: np.ndarray, start: tuple) -> tuple | None:
        """coarse_to_fine: node transforms of this graph from a first pass of the coarse
        graph, started where `start` puts the points and reaching as far as the fastest node
        moved in the last frame; None if that pass fails."""
        p, coarse = self.params, self._coarse
        points = self._contributions(*start).sum(axis=1)
        coarse.rotations, coarse.translations = coarse.transforms_onto(points)
        coarse.points = points
        reach = self.last_step_ / p.truncation_sigmas
        coarse.params = replace(coarse.params, initial_sigma2=max(p.initial_sigma2, reach ** 2))
        result = coarse.register_frame(observed)
        if result.status != STATUS_OK:
            return None
        return self.transforms_onto(result.points)

    def _carry_unseen_parts(self, state: '_EMState', start: tuple) -> None:
        """Parts without data this frame (out of sight, or lost and not recaptured) move
        rigidly with the tracked nodes they hang on, from where EM started them (the
        previous frame's state, or the predicted pose: `start` = (rotations, translations)),
        in place.

        With the robust smoothness such a part is torn off and, having nothing to follow,
        would stay where it was while the body walks on; the paper's stiff graph dragged it
        along. This keeps the drag, without letting the part pull on the tracked body."""
        graph = self.graph
        support = self._node_support(state.estep)
        start_rotations, start_translations = start
        before = graph.node_positions + start_translations
        after = graph.node_positions + state.translations
        for nodes, anchors in lost_parts(support, graph.edges):     # a few parts, not points
            if len(anchors) >= 3:
                rotation, shift = weighted_rigid_fit(before[anchors], after[anchors])
            else:
                rotation, shift = np.eye(3), (after[anchors] - before[anchors]).mean(axis=0)
            state.rotations[nodes] = np.einsum('ij,njk->nik', rotation, start_rotations[nodes])
            state.translations[nodes] = before[nodes] @ rotation.T + shift - graph.node_positions[nodes]
        state.points = self._contributions(state.rotations, state.translations).sum(axis=1)

    def _carried_on(self, stamp: float | None) -> np.ndarray:
        """(M, 3) m: where `inertia` starts a frame's EM: each registered point moved on along
        its last step by inertia x the step its last two steps agree on: the smallest of the
        last step, the earlier step's component along it, and the step that their change of
        speed predicts (2 x last - earlier), never backwards. Steps are scaled to frames by
        the stamps (s) when they are known (registered frames need not be evenly spaced);
        each point moves at most the E-step's reach at initial_sigma2.

        Why carry a step on: the data term pulls a limb only across its surface. Along a
        featureless limb a shifted model fits the observations as well, and only the limb's
        end pulls it on, so EM from the last pose lags a limb that swings or slides along
        itself, more each frame, until it is lost. Why only the agreed step: a registered
        step is the motion plus EM's correction of the frame before; carried on whole, a
        catch-up or a limb slowing to a stop overshoots, and a reversal is pushed the wrong
        way. The agreed step keeps a steady swing's pace and carries none of those."""
        p = self.params
        last, previous, earlier = self._stamps
        last_step = self.points - self._previous_points
        earlier_step = (self._previous_points - self._earlier_points) \
            * self._frames_between(last, previous, previous, earlier)
        length = np.linalg.norm(last_step, axis=1)
        direction = last_step / np.maximum(length, 1e-12)[:, None]
        along = np.einsum('ij,ij->i', earlier_step, direction)
        agreed = np.maximum(0.0, np.minimum.reduce([length, along, 2.0 * length - along]))
        step = p.inertia * self._frames_between(stamp, last, last, previous) * agreed
        reach = p.truncation_sigmas * np.sqrt(p.initial_sigma2)
        return self.points + direction * np.minimum(step, reach)[:, None]

    @staticmethod
    def _frames_between(end: float | None, start: float | None, reference_end: float | None,
                        reference_start: float | None) -> float:
        """The interval end - start (s) in units of the reference interval, to a tenth: a
        camera's stamps jitter by a fraction of a frame, and evenly spaced frames then count
        exactly as frames counted by index do (`run` and a lossless replay of the same bag
        register alike). 1 when a stamp is unknown (evenly spaced)."""
        if None in (end, start, reference_end, reference_start) or reference_end == reference_start:
            return 1.0
        return max(0.0, round((end - start) / (reference_end - reference_start), 1))

    def transforms_onto(self, points: np.ndarray) -> tuple:
        """Node transforms (rotations (J, 3, 3), translations (J, 3)) that carry the rest
        points onto `points` (M, 3) m, e.g. a pose predicted by a tracker: each node's
        weighted rigid fit of the points it carries (its blend weights). Exact for a rigid
        motion of the whole set; an approximation of a non-rigid one that EM refines."""
        points = np.asarray(points, dtype=np.float64)
        if points.shape != self.rest_points.shape or not np.isfinite(points).all():
            raise ValueError(f'start points must be finite ({len(self.rest_points)}, 3), got {points.shape}')
        rotations, centres = fit_weighted_segments(self.rest_points, points[None], self._blend.T)
        rotations, centres = rotations[0], centres[0]               # y = R q + c
        g = self.graph.node_positions
        # the graph's form: y = R (q - g) + g + T, so T = c + R g - g
        return rotations, centres + np.einsum('jik,jk->ji', rotations, g) - g

    # ----------------------------------------------------------------------------------
    def register_frame(self, observed: np.ndarray, start_points: np.ndarray | None = None,
                       stamp: float | None = None) -> FrameResult:
        """Register one frame's observed points (N, 3), metres: EM from the previous frame's
        state (carried on by its agreed step with `inertia`), or, with start_points (M, 3) (a
        predicted pose of the registered points, e.g. the live skeleton fit of a newer frame
        than the last registered one), from the node transforms that carry the rest points
        onto it (`transforms_onto`). stamp: the frame's time (s), which scales `inertia`'s
        step when frames are skipped; None = evenly spaced. A frame that is empty or
        diverges leaves the state as it was."""
        p = self.params
        observed = np.asarray(observed, dtype=np.float64)
        if observed.ndim != 2 or observed.shape[1] != 3:
            raise ValueError(f'observed points must be (N, 3), got {observed.shape}')
        observed = np.ascontiguousarray(observed[finite_rows(observed)])
        if len(observed) < p.min_points:
            return FrameResult(self.points.copy(), STATUS_EMPTY, float('nan'), 0, 0.0)
        if start_points is None and p.inertia > 0 and self._earlier_points is not None:
            start_points = self._carried_on(stamp)
        start = (self.rotations.copy(), self.translations.copy()) if start_points is None \
            else self.transforms_onto(start_points)

        view = ObservedView(observed) if p.visibility or p.free_space > 0 else None
        if self._extremities is not None and len(self._extremities):
            self._landmarks = self._match_landmarks(observed, self._contributions(*start).sum(axis=1))
        state = self._em_from(observed, view, start)
        if self._coarse is not None:
            coarse_start = self._coarse_start(observed, start)
            if coarse_start is not None:
                other = self._em_from(observed, view, coarse_start)
                if other.estep is not None and np.isfinite(other.sigma2) and (
                        state.estep is None or not np.isfinite(state.sigma2)
                        or self._frame_energy(observed, other) < self._frame_energy(observed, state)):
                    state = other
                    self.coarse_chosen_ += 1
        if p.smoothness == 'robust' and state.estep is not None and np.isfinite(state.sigma2):
            self._carry_unseen_parts(state, start)
        rotations, translations, points, sigma2 = state.rotations, state.translations, state.points, state.sigma2
        estep, iterations, energies = state.estep, state.iterations, state.energies
        matched_fraction = estep.Np / len(observed) if estep is not None else 0.0
        if not np.isfinite(sigma2) or sigma2 > p.max_sigma2 or matched_fraction < p.min_matched_fraction \
                or not np.isfinite(points).all():
            return FrameResult(self.points.copy(), STATUS_DIVERGED, float(sigma2), iterations,
                               float(matched_fraction), energies)
        self.last_step_ = float(np.max(np.linalg.norm(translations - self.translations, axis=1)))
        self._earlier_points, self._previous_points = self._previous_points, self.points
        self._stamps = (stamp, *self._stamps[:2])
        self.rotations, self.translations, self.points = rotations, translations, points
        return FrameResult(points.copy(), STATUS_OK, float(sigma2), iterations, float(matched_fraction), energies,
                           state.recaptured, len(self._landmarks))


def register_chains(registration: NonRigidRegistration, chains: list) -> tuple[list, NonRigidRegistration]:
    """Several chains of frames, each registered in order by its own copy of `registration`
    (a NonRigidRegistration of one rest pose, before its first frame), the chains at once on
    the core's thread pool: [[(FrameResult, seconds), ...] per chain], and the last chain's
    registration, from which the frames after it go on. chains: lists of (observed (N, 3) m,
    stamp s or None).

    Why: the frames held for the rest pose's choice are registered backward from the chosen
    one to the first and forward to the last, two chains that share nothing but the rest
    pose; on the way to the first skeleton they are all the work, and the time an EM
    iteration spends in numpy's, pykdtree's and SuperLU's calls (thread-safe, the GIL
    released) lets another thread run. Each chain gives exactly the results it gives alone."""
    if not chains:
        return [], registration
    copies = [registration] + [copy.deepcopy(registration) for _ in chains[1:]]

    def run(chain_and_registration):
        chain, chain_registration = chain_and_registration
        outcomes = []
        for observed, stamp in chain:
            started = time.perf_counter()
            result = chain_registration.register_frame(observed, None, stamp)
            outcomes.append((result, time.perf_counter() - started))
        return outcomes
    # the first chain (the backward one) on its own copy, the last on `registration` itself
    pairs = list(zip(chains, copies[1:] + copies[:1]))
    return parallel_map(run, pairs), pairs[-1][1]

"""Embedded deformation graph (Eq. 2)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from skel_extract_ros.core.deformation_graph import DeformationGraph


@pytest.fixture(scope='module')
def graph():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(600, 3)) * [0.3, 0.1, 0.05]
    return DeformationGraph.build(points, node_spacing=0.08, n_influence=4)


def test_weights_are_normalised_and_nonnegative(graph):
    assert graph.point_nodes.shape == (600, 4)
    assert (graph.point_weights >= 0).all()
    np.testing.assert_allclose(graph.point_weights.sum(axis=1), 1.0)
    # nodes lie on rest points, spaced about node_spacing apart
    assert 10 < graph.n_nodes < 300
    assert np.isin(graph.node_positions.view('f8,f8,f8'), graph.rest_points.view('f8,f8,f8')).all()


def test_identity_and_rigid_motions_are_reproduced_exactly(graph):
    n = graph.n_nodes
    identity = graph.deform(np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)))
    np.testing.assert_allclose(identity, graph.rest_points, atol=1e-12)
    rotation = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    shift = np.array([0.1, 0.2, -0.3])
    # a global rigid motion x -> R x + s expressed per node: R_j = R, T_j = R g_j + s - g_j
    translations = graph.node_positions @ rotation.T + shift - graph.node_positions
    moved = graph.deform(np.tile(rotation, (n, 1, 1)), translations)
    np.testing.assert_allclose(moved, graph.rest_points @ rotation.T + shift, atol=1e-12)


def test_colours_are_independent_sets(graph):
    colour_of = np.empty(graph.n_nodes, dtype=int)
    for c, nodes in enumerate(graph.colors):
        colour_of[nodes] = c
    assert sorted(np.concatenate(graph.colors)) == list(range(graph.n_nodes))
    assert (colour_of[graph.edges[:, 0]] != colour_of[graph.edges[:, 1]]).all()
    # nodes carrying a common point are graph neighbours (so in different colours)
    for nodes in graph.point_nodes[:50]:
        assert len(set(colour_of[nodes])) == len(nodes)


def test_bad_input():
    with pytest.raises(ValueError, match='node_spacing'):
        DeformationGraph.build(np.zeros((10, 3)), 0.0)
    with pytest.raises(ValueError, match='more than 4'):
        DeformationGraph.build(np.zeros((3, 3)), 0.1)

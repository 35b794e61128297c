"""The Sim(3) pose graph: a drifting chain of similarity transforms closed by one loop edge."""

import numpy as np
import pytest

from ffrecon.errors import InputError
from ffrecon.geometry.alignment import Sim3
from ffrecon.geometry.pose_graph import PoseGraphOptions, Sim3Edge, optimize_pose_graph
from ffrecon.geometry.rotations import axis_angle_to_matrix, rotation_angle_deg


def _turn(deg: float, scale: float = 1.0, shift=(0.0, 0.0, 0.0)) -> Sim3:
    return Sim3(scale, axis_angle_to_matrix(np.array([0.0, 0.0, np.deg2rad(deg)])), np.array(shift, np.float64))


def _chain(truth: list[Sim3], link_error: Sim3) -> tuple[list[Sim3], list[Sim3Edge]]:
    """Sequential edges measured with the same small error each, and the nodes chained from them (drifted)."""
    edges, nodes = [], [truth[0]]
    for k in range(len(truth) - 1):
        measured = link_error.compose(truth[k + 1].inverse().compose(truth[k]))  # b_from_a, a little off
        edges.append(Sim3Edge(k, k + 1, measured))
        nodes.append(nodes[-1].compose(measured.inverse()))
    return nodes, edges


def test_a_loop_edge_spreads_the_chains_drift_over_its_links():
    """20 nodes on a circle of radius 5 (ground truth), each link measured 0.5 deg and 1 % off: chained, the
    last node is 9.5 deg and a scale of 1.2 away; an exact loop edge from the first to the last brings every
    node within about one link's error, and every edge then carries the same share of the disagreement."""
    truth = [_turn(18.0 * k, 1.0, (5 * np.cos(0.3 * k), 5 * np.sin(0.3 * k), 0.0)) for k in range(20)]
    nodes, edges = _chain(truth, _turn(0.5, 1.01, (0.02, 0.0, 0.0)))
    before = [rotation_angle_deg((n.rotation.T @ t.rotation)[None])[0] for n, t in zip(nodes, truth)]
    assert before[-1] == pytest.approx(9.5, abs=0.01)
    loop = Sim3Edge(0, 19, truth[19].inverse().compose(truth[0]))
    result = optimize_pose_graph(nodes, [*edges, loop], length_scale=1.0)
    after = [rotation_angle_deg((n.rotation.T @ t.rotation)[None])[0] for n, t in zip(result.world_from_node, truth)]
    assert max(after) < 0.6  # from 9.5 deg at the end of the chain (measured: at most 0.43)
    np.testing.assert_array_equal(result.world_from_node[0].matrix(), nodes[0].matrix())  # the gauge stays
    scales = [n.scale for n in result.world_from_node]
    assert abs(np.log(scales[-1])) < 0.02 < abs(np.log(nodes[-1].scale))
    assert result.cost_after < 0.1 * result.cost_before and 1 <= result.iterations <= 20
    # Spread evenly: the 9.5 deg that the links and the loop disagree by falls on all 20 edges alike (the loop
    # edge takes its 1/20 share, not all of it), so each node is off by little more than one link's error.
    assert result.edge_rotation_deg == pytest.approx(9.5 / 20, abs=0.06)


def test_consistent_edges_leave_the_nodes_where_they_are_and_bad_edges_are_refused():
    truth = [_turn(10.0 * k, 1.0 + 0.1 * k, (k, 0.0, 0.0)) for k in range(4)]
    nodes, edges = _chain(truth, Sim3.identity())
    result = optimize_pose_graph(nodes, [*edges, Sim3Edge(0, 3, truth[3].inverse().compose(truth[0]))], 2.0)
    for got, want in zip(result.world_from_node, truth):
        np.testing.assert_allclose(got.matrix(), want.matrix(), atol=1e-9)
    assert result.cost_before < 1e-20 and result.edge_rotation_deg.max() < 1e-6
    with pytest.raises(InputError, match="distinct nodes"):
        optimize_pose_graph(nodes, [Sim3Edge(0, 4, Sim3.identity())], 1.0)
    with pytest.raises(InputError, match="max_iterations"):
        PoseGraphOptions(max_iterations=0)

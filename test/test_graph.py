"""The graph builder on hand-made traffic (paper 000, Section 2.2; docs/design.md, "Graph")."""
import numpy as np
import pytest

from exit_decision.config import GraphConfig
from exit_decision.graph import GraphBuilder, GraphCapacityError
from exit_decision.traffic import INTENTION_LEFT, INTENTION_RIGHT

from conftest import make_vehicle


def builder(max_vehicles=6, sensing_range=30.0):
    config = GraphConfig(max_vehicles=max_vehicles, sensing_range=sensing_range, feature_set='paper')
    return GraphBuilder(config, road_length=500.0, speed_scale=25.0)


def test_features_are_normalised_one_hot_rows():
    graph = builder().build([
        make_vehicle('a', 'CAV', lane=2, position=100.0, speed=25.0, intention=INTENTION_RIGHT),
        make_vehicle('b', 'HV1', lane=0, position=250.0, speed=12.5, intention=INTENTION_LEFT),
    ])
    np.testing.assert_allclose(graph.features[0], [1.0, 0.2, 0, 0, 1, 0, 1, 0])
    np.testing.assert_allclose(graph.features[1], [0.5, 0.5, 1, 0, 0, 1, 0, 0])
    assert not graph.features[2:].any(), 'absent rows are zero'
    assert graph.vehicle_ids[:3] == ('a', 'b', '')


def test_adjacency_rules():
    graph = builder().build([
        make_vehicle('cav1', 'CAV', position=100.0),
        make_vehicle('cav2', 'CAV', lane=2, position=400.0),    # far: still linked to cav1
        make_vehicle('hv_near', 'HV2', lane=1, position=125.0),  # 25 m from cav1, other lane
        make_vehicle('hv_far', 'HV1', position=140.0),           # 40 m from cav1
        make_vehicle('hv_near2', 'HV3', position=110.0),         # near hv_near: HVs never linked
    ])
    a = graph.adjacency
    assert (a == a.T).all()
    assert (np.diag(a)[:5] == 1).all() and not np.diag(a)[5:].any()
    assert a[0, 1] == 1, 'every CAV with every CAV'
    assert a[0, 2] == 1 and a[0, 4] == 1, 'CAV with HVs in sensing range, any lane'
    assert a[0, 3] == 0, 'HV beyond the sensing range'
    assert a[2, 4] == 0 and a[2, 3] == 0, 'never HV with HV'
    np.testing.assert_array_equal(graph.cav_mask[:5], [1, 1, 0, 0, 0])


def test_a_vehicle_keeps_its_slot_and_freed_slots_are_reused():
    b = builder()
    first = b.build([make_vehicle('a'), make_vehicle('b'), make_vehicle('c')])
    assert first.vehicle_ids[:3] == ('a', 'b', 'c')
    second = b.build([make_vehicle('c'), make_vehicle('d')])   # a and b left; order changed
    assert second.vehicle_ids[2] == 'c'
    assert second.vehicle_ids[0] == 'd', 'lowest free slot'
    b.reset()
    assert b.build([make_vehicle('z')]).vehicle_ids[0] == 'z'


def test_more_vehicles_than_rows_is_an_error_naming_the_setting():
    with pytest.raises(GraphCapacityError, match='max_vehicles'):
        builder(max_vehicles=2).build([make_vehicle(str(i)) for i in range(3)])

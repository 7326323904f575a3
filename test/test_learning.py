"""Networks, m-step targets, double-Q choice, soft update and checkpoints on hand-made data."""
import numpy as np
import pytest
import torch

from exit_decision.actions import NO_ACTION
from exit_decision.config import load_project
from exit_decision.errors import PolicyError
from exit_decision.graph import TrafficGraph
from exit_decision.learning.agent import GraphQAgent, UpdateSettings
from exit_decision.learning.replay import DecisionRecord, EpisodeAccumulator, ReplayBuffer, scored_rewards
from exit_decision.learning.sampling import WeightSampler, dirichlet_rows
from exit_decision.model.networks import GraphQNetwork, NetworkShape, SelectedRows, normalize_adjacency
from exit_decision.learning.checkpoints import save_policy
from exit_decision.model.modes import Mode
from exit_decision.model.policy import PolicyController, load_policy
from exit_decision.reward import weights_of_input
from exit_decision.traffic import TrafficSnapshot

A = 4


def test_gcn_normalisation_on_a_hand_made_graph():
    adjacency = torch.tensor([[[1, 1, 0], [1, 1, 1], [0, 1, 1]]], dtype=torch.float32)
    degree = torch.tensor([2.0, 3.0, 2.0])
    expected = adjacency[0] / torch.sqrt(degree[:, None] * degree[None, :])
    torch.testing.assert_close(normalize_adjacency(adjacency)[0], expected)
    empty_row = torch.tensor([[[1, 0], [0, 0]]], dtype=torch.float32)
    assert normalize_adjacency(empty_row)[0, 1].abs().sum() == 0, 'absent rows stay zero'


def test_q_network_shapes_and_that_n_is_free():
    net = GraphQNetwork(NetworkShape(num_features=5, num_actions=A))
    for n in (3, 60):
        q = net(torch.rand(2, n, 5), torch.eye(n).expand(2, n, n))
        assert q.shape == (2, n, A)
    rows = torch.tensor([[0, 1], [1, 2]])
    features, adjacency = torch.rand(2, 3, 5), torch.ones(2, 3, 3)
    torch.testing.assert_close(net.cav_q_values(features, SelectedRows.of(adjacency, rows)), net(features, adjacency)[rows[:, 0], rows[:, 1]])


def _shapes() -> dict[str, dict]:
    """The network of every method of config/training.yaml, plain and mode-conditioned, and the
    corners the methods do not reach (no hidden layer at all; no encoder; dueling with a GCN)."""
    from exit_decision.config import default_config_dir
    shapes = {}
    for name, method in load_project(default_config_dir()).training.methods.items():
        net = method.network
        shape = dict(encoder=tuple(net.encoder), gcn=net.gcn, head=tuple(net.head), dueling=net.dueling,
                     adjacency_input=net.adjacency_input, num_nodes=60 if net.adjacency_input else 0)
        shapes[name] = shape
        shapes[name + '_conditioned'] = dict(shape, num_weights=6)
    shapes.update(bare=dict(encoder=(), head=()), no_encoder_conditioned=dict(encoder=(), num_weights=6),
                  dueling_gcn=dict(dueling=True, num_weights=6))
    return shapes


@pytest.mark.parametrize('shape', list(_shapes().values()), ids=list(_shapes()))
def test_one_graph_inference_is_bit_identical_to_the_forward_pass(shape):
    """The decision node, evaluation and acting decide with ``one_graph``, training learns with
    ``forward``: a decision must not depend on which ran (nor on the row count: N = 3 takes
    torch's small-matrix kernels), on the call before, or on when the weights last changed."""
    torch.manual_seed(0)
    net = GraphQNetwork(NetworkShape(num_features=20, num_actions=81, **shape))
    rng = np.random.default_rng(0)

    def expected(features, adjacency, w):
        return net(torch.from_numpy(features)[None], torch.from_numpy(adjacency)[None],
                   None if w is None else torch.tensor(w, dtype=torch.float32)[None])[0].detach().numpy()
    kept = []
    for n in ((60,) if shape.get('adjacency_input') else (60, 3, 60)):
        for weights in (np.array([0.25, 0.35, 0.15, 0.25, 0.6, 0.4]), np.array([0.2, 0.2, 0.25, 0.35, 0.4, 0.6])):
            features = rng.normal(size=(n, 20)).astype(np.float32)
            adjacency = (rng.random((n, n)) < 0.2).astype(np.uint8)
            adjacency = np.maximum(adjacency, adjacency.T) | np.eye(n, dtype=np.uint8)
            adjacency[n - 1] = adjacency[:, n - 1] = 0                 # an absent vehicle: no edge at all
            w = weights if net.conditioned else None
            q = net.one_graph(features, adjacency, w)
            assert np.array_equal(q, expected(features, adjacency, w))
            kept.append((q, q.copy()))
    assert all(np.array_equal(q, copy) for q, copy in kept), 'a later call changed Q values already returned'
    with torch.no_grad():   # weights changed in place (an optimizer step, load_state_dict) after the first call
        for parameter in net.parameters():
            parameter.add_(0.01)
    assert np.array_equal(net.one_graph(features, adjacency, w), expected(features, adjacency, w))
    if net.conditioned:
        with pytest.raises(ValueError, match='needs the mode weights'):
            net.one_graph(features, adjacency)
    with pytest.raises(ValueError, match='do not fit'):
        net.one_graph(features, adjacency.astype(np.float32), w)


@pytest.mark.parametrize('shape', list(_shapes().values()), ids=list(_shapes()))
def test_learning_values_the_selected_rows_as_the_forward_pass_does(shape):
    """Learning values only the rows it learns from (``cav_q_values``): the same values and
    gradients as ``forward`` on those rows, up to rounding, on a batch with absent vehicles."""
    torch.manual_seed(0)
    net = GraphQNetwork(NetworkShape(num_features=8, num_actions=A, **shape))
    n = shape.get('num_nodes') or 12
    adjacency = (torch.rand(4, n, n) < 0.3).to(torch.uint8)
    adjacency = torch.maximum(adjacency, adjacency.transpose(1, 2)) | torch.eye(n, dtype=torch.uint8)
    adjacency[:, n - 3:] = adjacency[:, :, n - 3:] = 0          # absent vehicles: no edge at all
    features, rows = torch.rand(4, n, 8), torch.tensor([[0, 1], [0, 4], [2, 0], [3, n - 4], [3, 2]])
    weights = torch.rand(4, 6) if shape.get('num_weights') else None
    selected = SelectedRows.of(adjacency, rows)
    expected = net(features, adjacency, weights)[rows[:, 0], rows[:, 1]]
    values = net.cav_q_values(features, selected, weights)
    torch.testing.assert_close(values, expected)
    stored = SelectedRows.of(adjacency, rows, adjacency.sum(-1, dtype=torch.int16))   # degrees as the replay keeps them
    torch.testing.assert_close(net.cav_q_values(features, stored, weights), values)
    grads = torch.autograd.grad(values.sum(), list(net.parameters()), allow_unused=True)
    expected_grads = torch.autograd.grad(expected.sum(), list(net.parameters()), allow_unused=True)
    for grad, expected_grad in zip(grads, expected_grads):
        if expected_grad is not None:
            torch.testing.assert_close(grad, expected_grad)


def test_an_isolated_row_is_not_influenced_by_others():
    net = GraphQNetwork(NetworkShape(num_features=3, num_actions=A))
    features = torch.rand(1, 3, 3)
    isolated = torch.eye(3).unsqueeze(0)
    q1 = net(features, isolated)
    features2 = features.clone()
    features2[0, 1:] = torch.rand(2, 3)
    torch.testing.assert_close(net(features2, isolated)[0, 0], q1[0, 0])


def graph(ids, n=3, f=2, cavs=None):
    cav_mask = np.array([bool(i) for i in ids]) if cavs is None else np.array(cavs)
    return TrafficGraph(np.full((n, f), len(ids[0]), np.float32), np.eye(n, dtype=np.uint8), cav_mask, tuple(ids))


def vector(value):
    """A reward vector that any mode with k_result * k_I = 1 scores as ``value``."""
    v = np.zeros((4, 2))
    v[0, 0] = value
    return v


def record(ids, reward, actions=(0, NO_ACTION, NO_ACTION), shared=0.0):
    own = np.zeros((3, 4, 2))
    own[0] = vector(reward)
    return DecisionRecord(graph(ids), np.array(actions), np.ones((3, A), bool), own, vector(shared))


def scored(transition, row=0):
    return transition.returns[row, 0, 0]


def test_m_step_target_with_an_episode_end_inside_the_window():
    gamma = 0.5
    acc = EpisodeAccumulator(steps=3, gamma=gamma)
    ids = ('a', '', '')
    assert acc.add(record(ids, 1.0)) == []
    assert acc.add(record(ids, 2.0)) == []
    assert acc.add(record(ids, 4.0)) == []
    first = acc.add(record(('b', '', ''), 8.0))         # t=0 -> t=3 complete
    assert len(first) == 1
    assert scored(first[0]) == pytest.approx(1 + 0.5 * 2 + 0.25 * 4)
    assert first[0].discount == pytest.approx(0.125)
    assert not first[0].alive[0], 'row 0 holds another vehicle at t+3: terminal for a'
    rest = acc.finish(DecisionRecord(graph(('b', '', '')), np.full(3, NO_ACTION), np.ones((3, A), bool)),
                      terminated=True)
    assert [round(scored(t), 6) for t in rest] == [2 + 0.5 * 4, 4, 8.0], 'a is not credited b\'s reward (row 0 from t=3)'
    assert [round(t.global_return[0, 0], 6) for t in rest] == [2 + 0.5 * 4 + 0.25 * 8, 4 + 0.5 * 8, 8.0]
    assert all(t.discount == 0.0 for t in rest), 'no bootstrap past the episode end'
    assert rest[2].alive[0], 'b is still there: only the episode end stops the bootstrap'


def test_each_acting_row_gets_its_own_terms_and_an_equal_share_of_the_rest():
    own = np.zeros((3, 4, 2))
    own[0], own[1], own[2] = vector(1.0), vector(3.0), vector(100.0)   # row 2 did not act
    rec = DecisionRecord(graph(('a', 'b', 'h')), np.array([0, 2, NO_ACTION]), np.ones((3, A), bool), own, vector(4.0))
    accumulator = EpisodeAccumulator(steps=1, gamma=0.9)
    assert accumulator.add(rec) == []
    (transition,) = accumulator.finish(record(('a', 'b', 'h'), 0.0), terminated=True)
    assert [scored(transition, row) for row in range(3)] == [1.0 + 2.0, 3.0 + 2.0, 0.0]
    assert transition.global_return[0, 0] == pytest.approx(1 + 3 + 100 + 4), 'the global return keeps every term'


def test_a_decision_where_no_cav_acted_gives_no_transition_but_its_reward_still_counts():
    acc = EpisodeAccumulator(steps=2, gamma=0.5)
    assert acc.add(record(('h', '', ''), 1.0, actions=(NO_ACTION,) * 3)) == []   # no CAV yet (SGRL: not the learner)
    acc.add(record(('a', '', ''), 2.0))
    assert acc.add(record(('a', '', ''), 4.0)) == [], 'the first decision is complete but nobody acted in it'
    (last, final) = acc.finish(record(('a', '', ''), 0.0), terminated=True)
    assert [scored(last), scored(final)] == [2 + 0.5 * 4, 4.0]


def test_truncated_episode_still_bootstraps():
    acc = EpisodeAccumulator(steps=3, gamma=0.5)
    acc.add(record(('a', '', ''), 1.0))
    (last,) = acc.finish(record(('a', '', ''), 0.0), terminated=False)
    assert last.discount == 0.5 and last.alive[0]


def make_batch(next_q_rows_alive=True):
    buffer = ReplayBuffer(4, num_nodes=3, num_features=2, num_actions=A)
    acc = EpisodeAccumulator(steps=1, gamma=0.9)
    acc.add(record(('a', '', ''), 1.0))
    mask = np.ones((3, A), bool)
    mask[0, 0] = False
    final = DecisionRecord(graph(('a' if next_q_rows_alive else 'z', '', '')), np.full(3, NO_ACTION), mask)
    (transition,) = acc.finish(final, terminated=False)
    buffer.add(transition)
    batch = buffer.sample(np.array([0]))
    batch['rewards'] = scored_rewards(batch, weights_of_input(np.array([[1.0, 0, 0, 0, 1.0, 0]])), 'own')
    return batch


def test_the_replay_gives_each_row_its_degree_with_the_adjacency():
    batch = make_batch()
    for prefix in ('', 'next_'):
        np.testing.assert_array_equal(batch[f'{prefix}degrees'], batch[f'{prefix}adjacency'].sum(-1))
        assert batch[f'{prefix}adjacency'].any(), 'a graph with edges'


class FixedNet(torch.nn.Module):
    """Q(s)[row] = the given vector, whatever the input."""

    def __init__(self, values):
        super().__init__()
        self.values = torch.tensor(values, dtype=torch.float32)

    def cav_q_values(self, features, selected, weights=None):
        return self.values.expand(len(selected.rows), A)


def agent_with(double, online_values, target_values):
    agent = GraphQAgent(NetworkShape(2, A), UpdateSettings(double, 1e-3, 0.05, 0.8, 10.0), seed=0)
    agent.online, agent.target = FixedNet(online_values), FixedNet(target_values)
    return agent


@pytest.mark.parametrize('double, expected_bootstrap', [
    (False, 7.0),     # GQN, DQN: the target net picks its own best allowed action (index 2: 7) and evaluates it
    (True, 5.0),      # MDGQN, DDQN: the online net picks (index 3), the target net evaluates it (5)
])
def test_double_q_action_choice_under_the_next_mask(double, expected_bootstrap):
    batch = {k: torch.from_numpy(v) for k, v in make_batch().items()}
    # action 0 is masked at s': its huge values must never be chosen
    agent = agent_with(double, online_values=[100.0, 0.0, 1.0, 3.0], target_values=[100.0, 1.0, 7.0, 5.0])
    targets = agent.td_targets(batch, torch.tensor([[0, 0]]))
    assert targets.item() == pytest.approx(1.0 + 0.9 * expected_bootstrap)


@pytest.mark.parametrize('double', [False, True])
def test_bootstrapping_on_the_prior_values_the_next_state_by_the_priors_option(double):
    """``bootstrap: prior``: the target takes the prior's option at s' (here 3), whatever the
    networks' greedy choice (2 for both): the network learns Q of the prior."""
    batch = {k: torch.from_numpy(v) for k, v in make_batch().items()}
    batch['prior_actions'] = torch.tensor([3])
    agent = agent_with(double, online_values=[100.0, 0.0, 9.0, 3.0], target_values=[100.0, 1.0, 7.0, 5.0])
    assert agent.td_targets(batch, torch.tensor([[0, 0]])).item() == pytest.approx(1.0 + 0.9 * 5.0)


def test_a_vehicle_that_left_gets_a_terminal_target():
    batch = {k: torch.from_numpy(v) for k, v in make_batch(next_q_rows_alive=False).items()}
    agent = agent_with(True, [0.0, 0.0, 1.0, 3.0], [0.0, 1.0, 7.0, 5.0])
    assert agent.td_targets(batch, torch.tensor([[0, 0]])).item() == pytest.approx(1.0)


def test_soft_update_moves_the_target_by_tau():
    agent = GraphQAgent(NetworkShape(2, A), UpdateSettings(False, 1e-3, 0.25, 0.8, 10.0), seed=0)
    before = [p.clone() for p in agent.target.parameters()]
    with torch.no_grad():
        for p in agent.online.parameters():
            p.add_(1.0)
    agent.soft_update()
    for old, new, online in zip(before, agent.target.parameters(), agent.online.parameters()):
        torch.testing.assert_close(new, 0.75 * old + 0.25 * online)


def test_margin_loss_pushes_the_demonstrated_action_up():
    batch = make_batch()
    agent = GraphQAgent(NetworkShape(2, A), UpdateSettings(True, 1e-2, 0.05, 0.8, 10.0), seed=0)
    demo = np.array([True])
    for _ in range(200):
        stats, _ = agent.update(batch, demo, margin_weight=1.0)
    q = agent.online(torch.from_numpy(batch['features']), torch.from_numpy(batch['adjacency']))[0, 0]
    assert int(q.argmax()) == 0, 'the demonstrated action (0) is the greedy one'
    assert np.isfinite(stats['loss'])


def test_checkpoint_round_trip_and_errors(tmp_path):
    net = GraphQNetwork(NetworkShape(num_features=2, num_actions=A))
    metadata = {'algorithm': 'mdgqn', 'mode': 'AGGI', 'num_nodes': 3, 'feature_set': 'paper',
                'decision_interval': 5, 'action_grid': {'lane_changes': [-1, 0, 1], 'acceleration_min': -1.0,
                                                        'acceleration_max': 0.0, 'acceleration_step': 1.0}}
    save_policy(tmp_path / 'p.pt', net, metadata)
    policy = load_policy(tmp_path / 'p.pt')
    g = graph(('a', 'b', ''))
    np.testing.assert_allclose(policy.q_values(g, TrafficSnapshot([])), net(torch.from_numpy(g.features)[None],
                                                       torch.from_numpy(g.adjacency)[None])[0].detach().numpy())
    assert policy.metadata['mode'] == 'AGGI' and policy.grid.size == 6
    with pytest.raises(PolicyError, match='no such policy file'):
        load_policy(tmp_path / 'missing.pt')
    (tmp_path / 'bad.pt').write_bytes(b'not a checkpoint')
    with pytest.raises(PolicyError, match='bad.pt: not a readable policy checkpoint'):
        load_policy(tmp_path / 'bad.pt')
    with pytest.raises(PolicyError, match='trained with num_nodes=3, the configuration has 60'):
        policy.check_compatible(load_project())


def test_a_conditioned_network_answers_per_weight_vector():
    net = GraphQNetwork(NetworkShape(num_features=2, num_actions=A, num_weights=6))
    features, adjacency = torch.rand(2, 3, 2), torch.eye(3).expand(2, 3, 3)
    aggressive = torch.tensor([[0.25, 0.35, 0.15, 0.25, 0.6, 0.4]] * 2)
    conservative = torch.tensor([[0.2, 0.2, 0.25, 0.35, 0.4, 0.6]] * 2)
    assert not torch.allclose(net(features, adjacency, aggressive), net(features, adjacency, conservative))
    rows = torch.tensor([[0, 1], [1, 2]])
    torch.testing.assert_close(net.cav_q_values(features, SelectedRows.of(adjacency, rows), aggressive),
                               net(features, adjacency, aggressive)[rows[:, 0], rows[:, 1]])
    with pytest.raises(ValueError, match='needs the mode weights'):
        net(features, adjacency)


def test_a_conditioned_checkpoint_decides_for_the_weights_of_its_mode(tmp_path):
    net = GraphQNetwork(NetworkShape(num_features=2, num_actions=A, num_weights=6))
    save_policy(tmp_path / 'c.pt', net, {'algorithm': 'mdgqn', 'mode': 'conditioned', 'action_grid': {
        'lane_changes': [-1, 0, 1], 'acceleration_min': -1.0, 'acceleration_max': 0.0, 'acceleration_step': 1.0}})
    policy = load_policy(tmp_path / 'c.pt')
    assert policy.conditioned
    g = graph(('a', 'b', ''))
    w = np.array([0.25, 0.35, 0.15, 0.25, 0.6, 0.4])
    expected = net(torch.from_numpy(g.features)[None], torch.from_numpy(g.adjacency)[None],
                   torch.tensor(w, dtype=torch.float32)[None])[0].detach().numpy()
    np.testing.assert_allclose(policy.q_values(g, TrafficSnapshot([]), w), expected, rtol=1e-6)
    controller = PolicyController(policy, shield=None)
    np.testing.assert_array_equal(controller.network_weights(Mode('custom', w)), w)


def test_relabelled_rewards_score_each_transition_under_its_own_weights():
    batch = make_batch()
    batch = {**batch, 'returns': np.concatenate([batch['returns']] * 2),
             'global_returns': np.concatenate([batch['global_returns']] * 2)}
    weights = np.array([[1.0, 0, 0, 0, 1.0, 0], [0.5, 0.5, 0, 0, 0.5, 0.5]])
    rewards = scored_rewards(batch, weights_of_input(weights), 'own')
    assert rewards[0, 0] == pytest.approx(1.0) and rewards[1, 0] == pytest.approx(0.25)


def test_relabelling_weights_follow_the_dirichlet_around_each_mode():
    """The batch's stick-breaking Dirichlet has the Dirichlet's mean and variance, and every
    relabelled weight vector stays on the simplex (decision shares and the incentive pair)."""
    rng = np.random.default_rng(0)
    alpha = np.tile([20.0, 10.0, 5.0, 15.0], (40000, 1))
    draws = dirichlet_rows(rng, alpha)
    total = alpha[0].sum()
    mean = alpha[0] / total
    np.testing.assert_allclose(draws.mean(0), mean, atol=3e-3)
    np.testing.assert_allclose(draws.var(0), mean * (1 - mean) / (total + 1), rtol=0.05)
    np.testing.assert_allclose(draws.sum(1), 1.0, atol=1e-12)
    config = load_project()
    sampler = WeightSampler(config, ['AGGI', 'CONP'], exact_share=0.25, concentration=30.0, rng=rng)
    weights = sampler.sample(500)
    assert (weights >= 0).all()
    np.testing.assert_allclose(weights[:, :4].sum(1), 1.0, atol=1e-9)
    np.testing.assert_allclose(weights[:, 4] + weights[:, 5], 1.0, atol=1e-9)
    exact = (weights[:, None, :] == sampler.anchors[None]).all(-1).any(-1)
    assert 0.15 < exact.mean() < 0.35, 'a quarter of the draws are a mode exactly'

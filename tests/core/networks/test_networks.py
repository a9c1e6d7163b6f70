"""The recurrent interface: carries reset at episode starts; GTrXL never looks across one; the
networks that replay a sequence at once (GTrXL, memoryless MLPs) give the step-by-step numbers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quicknav_core.config import GTrXLNetwork, LSTMNetwork, MLPNetwork
from quicknav_core.networks import make_network

NETWORKS = {
    "mlp": MLPNetwork(hidden_sizes=(16,)),
    "mlp-memory": MLPNetwork(hidden_sizes=(16,), memory_size=8),
    "mlp-frames": MLPNetwork(hidden_sizes=(16,), frames=3),
    "mlp-strided": MLPNetwork(hidden_sizes=(16,), frames=3, frame_stride=2),
    "lstm": LSTMNetwork(num_layers=2, hidden_size=6),
    "gtrxl": GTrXLNetwork(embed_size=8, num_heads=2, head_size=4, num_layers=2, memory_length=5),
}
OBS = 7


def _init(name, batch=3):
    net = make_network(NETWORKS[name], obs_dim=OBS)
    carry = net.initial_carry(batch)
    obs = jnp.ones((batch, OBS))
    params = net.init(jax.random.PRNGKey(0), carry, obs, jnp.ones((batch,), bool))
    return net, params


def _run(net, params, obs_seq, start_seq):
    """Step through a (T, B, O) sequence, returning means (T, B, A) and values (T, B)."""

    def step(carry, xs):
        obs, start = xs
        carry, out = net.apply(params, carry, obs, start)
        return carry, (out.mean, out.value)

    _, (mean, value) = jax.lax.scan(step, net.initial_carry(obs_seq.shape[1]), (obs_seq, start_seq))
    return np.asarray(mean), np.asarray(value)


@pytest.mark.parametrize("name", list(NETWORKS))
def test_carry__resets_exactly_at_episode_start(name):
    net, params = _init(name)
    key = jax.random.PRNGKey(1)
    obs = jax.random.normal(key, (3, OBS))
    fresh_carry = net.initial_carry(3)
    # a carry full of history
    busy = jax.tree.map(lambda x: jax.random.normal(key, x.shape).astype(x.dtype) if x.dtype != bool
                        else jnp.ones_like(x), fresh_carry)  # fmt: skip
    start = jnp.array([True, False, True])
    _, out_busy = net.apply(params, busy, obs, start)
    _, out_fresh = net.apply(params, fresh_carry, obs, jnp.ones(3, bool))
    np.testing.assert_allclose(
        np.asarray(out_busy.mean)[start], np.asarray(out_fresh.mean)[start], atol=1e-6
    )
    if name != "mlp":  # memoryless: history never matters
        assert not np.allclose(np.asarray(out_busy.mean)[1], np.asarray(out_fresh.mean)[1])


@pytest.mark.parametrize("name", ["mlp-memory", "mlp-frames", "lstm", "gtrxl"])
def test_memory__earlier_episode_cannot_influence_current_output(name):
    net, params = _init(name, batch=2)
    t_len, boundary = 12, 6
    obs = jax.random.normal(jax.random.PRNGKey(2), (t_len, 2, OBS))
    start = jnp.zeros((t_len, 2), bool).at[0].set(True).at[boundary].set(True)
    mean_a, value_a = _run(net, params, obs, start)
    # change every observation of the previous episode
    obs_b = obs.at[:boundary].add(3.0)
    mean_b, value_b = _run(net, params, obs_b, start)
    np.testing.assert_allclose(mean_a[boundary:], mean_b[boundary:], atol=1e-6)
    np.testing.assert_allclose(value_a[boundary:], value_b[boundary:], atol=1e-6)
    # while inside an episode, the past does matter (the memory is real)
    assert not np.allclose(mean_a[1:boundary], mean_b[1:boundary])


def test_gtrxl__memory_window_is_memory_length():
    net, params = _init("gtrxl", batch=1)
    m = NETWORKS["gtrxl"].memory_length
    t_len = m + 8
    obs = jax.random.normal(jax.random.PRNGKey(3), (t_len, 1, OBS))
    start = jnp.zeros((t_len, 1), bool).at[0].set(True)
    mean_a, _ = _run(net, params, obs, start)
    obs_b = obs.at[0].add(5.0)  # the very first step falls out of layer 0's memory after m steps
    mean_b, _ = _run(net, params, obs_b, start)
    assert not np.allclose(mean_a[1], mean_b[1])
    # layer 1 remembers layer-0 outputs for another m steps; after 2m steps nothing is left
    np.testing.assert_allclose(mean_a[2 * m + 1 :], mean_b[2 * m + 1 :], atol=1e-6)


@pytest.mark.parametrize("memory_length", [5, 32])
def test_gtrxl__whole_sequence_at_once_equals_step_by_step(memory_length):
    """The training replay runs a GTrXL sequence as one banded attention per layer; it must give
    the step-by-step numbers from any carry, with episode starts anywhere (first step included)."""
    cfg = NETWORKS["gtrxl"].model_copy(update={"memory_length": memory_length})
    net = make_network(cfg)
    batch, t_len = 4, 40
    # compiled, as training runs them (op by op, init and the whole-sequence call took 3-4 s more)
    params = jax.jit(net.init)(jax.random.PRNGKey(1), net.initial_carry(batch), jnp.ones((batch, OBS)),
                               jnp.ones((batch,), bool))  # fmt: skip
    # a carry from a warm-up whose episodes started at different times (some memory slots invalid)
    warm_obs = jax.random.normal(jax.random.PRNGKey(2), (7, batch, OBS))
    warm_start = jnp.zeros((7, batch), bool).at[0].set(True).at[4, 1].set(True)

    def step(carry, xs):
        carry, out = net.apply(params, carry, *xs)
        return carry, out

    carry0, _ = jax.lax.scan(step, net.initial_carry(batch), (warm_obs, warm_start))
    obs = jax.random.normal(jax.random.PRNGKey(3), (t_len, batch, OBS))
    start = (jax.random.uniform(jax.random.PRNGKey(4), (t_len, batch)) < 0.08).at[0, 2].set(True)
    _, by_step = jax.lax.scan(step, carry0, (obs, start))
    same_carry, at_once = jax.jit(net.apply)(params, carry0, obs, start)
    for kept, before in zip(jax.tree.leaves(same_carry), jax.tree.leaves(carry0), strict=True):
        np.testing.assert_array_equal(np.asarray(kept), np.asarray(before))  # the carry, untouched
    for a, b in ((at_once.mean, by_step.mean), (at_once.value, by_step.value), (at_once.log_std, by_step.log_std)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-5, atol=2e-6)

    # and gradients through it agree (what PPO's loss differentiates); compiled as training
    # compiles them (run op by op, the two gradients took half a minute on 2 cores)
    def loss(p, run):
        return jnp.sum(run(p).mean ** 2) + jnp.sum(run(p).value)

    def seq(p):
        return net.apply(p, carry0, obs, start)[1]

    def steps(p):
        return jax.lax.scan(lambda c, xs: net.apply(p, c, *xs), carry0, (obs, start))[1]

    g_seq = jax.jit(jax.grad(lambda p: loss(p, seq)))(params)
    g_step = jax.jit(jax.grad(lambda p: loss(p, steps)))(params)
    for a, b in zip(jax.tree.leaves(g_seq), jax.tree.leaves(g_step), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-3, atol=1e-5)


def test_mlp_frames__reads_exactly_the_last_frames_observations():
    """frames=3: the output at t depends on obs[t-2..t] and on nothing older; at an episode's
    second step the first observation stands in for the one not yet seen."""
    net, params = _init("mlp-frames", batch=1)
    t_len = 8
    obs = jax.random.normal(jax.random.PRNGKey(5), (t_len, 1, OBS))
    start = jnp.zeros((t_len, 1), bool).at[0].set(True)
    mean_a, _ = _run(net, params, obs, start)
    mean_b, _ = _run(net, params, obs.at[2].add(4.0), start)
    np.testing.assert_allclose(mean_a[:2], mean_b[:2], atol=1e-6)  # before it: untouched
    for t in (2, 3, 4):  # it is read at t = 2, 3, 4 ...
        assert not np.allclose(mean_a[t], mean_b[t])
    np.testing.assert_allclose(mean_a[5:], mean_b[5:], atol=1e-6)  # ... and forgotten after
    # at step 1 the MLP reads [obs1, obs0, obs0]: the same as a 3-frame input built by hand
    x = jnp.concatenate([obs[1], obs[0], obs[0]], axis=-1)
    plain = make_network(MLPNetwork(hidden_sizes=(16,)))
    out = plain.apply(params, (), x, jnp.zeros((1,), bool))[1]
    np.testing.assert_allclose(np.asarray(out.mean), mean_a[1], rtol=1e-5, atol=1e-6)


def test_mlp_frames__a_stride_reads_every_other_observation():
    """frames=3, frame_stride=2: the output at t reads obs[t], obs[t-2] and obs[t-4] (the
    episode's first observation standing in for those before it), nothing between them."""
    net, params = _init("mlp-strided", batch=1)
    assert net.initial_carry(2).shape == (2, 4, OBS)
    t_len = 9
    obs = jax.random.normal(jax.random.PRNGKey(5), (t_len, 1, OBS))
    start = jnp.zeros((t_len, 1), bool).at[0].set(True)
    mean_a, _ = _run(net, params, obs, start)
    mean_b, _ = _run(net, params, obs.at[2].add(4.0), start)
    changed = [t for t in range(t_len) if not np.allclose(mean_a[t], mean_b[t], atol=1e-6)]
    assert changed == [2, 4, 6], changed
    plain = make_network(MLPNetwork(hidden_sizes=(16,)))
    for t, read in ((1, (1, 0, 0)), (3, (3, 1, 0)), (7, (7, 5, 3))):
        x = jnp.concatenate([obs[i] for i in read], axis=-1)
        out = plain.apply(params, (), x, jnp.zeros((1,), bool))[1]
        np.testing.assert_allclose(np.asarray(out.mean), mean_a[t], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", ["mlp", "mlp-frames", "mlp-strided"])
def test_mlp__whole_sequence_at_once_equals_step_by_step(name):
    """A memoryless MLP (past frames or not) replays a (T, B) sequence in one call: the same
    numbers as step by step from any carry, episode starts anywhere."""
    net, params = _init(name, batch=4)
    assert net.parallel_sequence

    def step(carry, xs):
        return net.apply(params, carry, *xs)

    warm = jax.random.normal(jax.random.PRNGKey(2), (3, 4, OBS))
    carry0, _ = jax.lax.scan(step, net.initial_carry(4), (warm, jnp.zeros((3, 4), bool).at[0].set(True)))
    obs = jax.random.normal(jax.random.PRNGKey(3), (20, 4, OBS))
    start = (jax.random.uniform(jax.random.PRNGKey(4), (20, 4)) < 0.15).at[0, 2].set(True).at[1, 1].set(True)
    _, by_step = jax.lax.scan(step, carry0, (obs, start))
    _, at_once = net.apply(params, carry0, obs, start)
    for a, b in ((at_once.mean, by_step.mean), (at_once.value, by_step.value)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-5, atol=2e-6)

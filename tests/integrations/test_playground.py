"""jaxmetrics.playground on MuJoCo Playground's CartpoleBalance (MJX, CPU) under lax.scan
with Playground's auto-reset and action_repeat=2.

The reference is a hand-written float64 unroll of the unwrapped env: every physics
sub-step is stepped in a Python loop, episodes end at the time limit, and envs that are
done go back to their first state, as Playground's `BraxAutoResetWrapper` does. The
envs in Playground's own `wrap_for_brax_training` are run on the same actions for the
info keys it writes.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco_playground import registry, wrapper

import jaxmetrics as jm
import jaxmetrics.playground as jmp

ENV = "CartpoleBalance"
NUM_ENVS = 4
STEPS = 13
REPEAT = 2
EPISODE_LENGTH = 9  # sub-steps: episodes of 5 env steps (10 sub-steps, Brax's units)
STATS = ("mean", "count", jm.window(64))
COMPONENTS = ("reward/upright", "reward/centered")
BRAX_INFO = ("done", "steps", "truncation")  # what `rollout` records, per env step


def load_env():
    config = registry.get_default_config(ENV)
    config.impl = "jax"  # MJX's JAX implementation: Warp's CPU kernels take minutes to build
    return registry.load(ENV, config=config)


def make_metrics():
    return jm.Metrics(
        terms={
            "return": jmp.episode_return(stats=STATS),
            "length": jmp.episode_length(stats=STATS),
            "truncated": jmp.truncation_rate(stats=STATS),
            "qvel": jmp.joint_velocity(stats=STATS),
            "pole_speed_max": jmp.joint_velocity([1], ord=np.inf, reduce="max", stats=STATS),
            "effort": jmp.control_effort(stats=STATS),
            **jmp.state_metrics(COMPONENTS, stats=STATS),
        }
    )


def actions():
    rng = np.random.default_rng(0)
    return rng.uniform(-1.0, 1.0, (STEPS, NUM_ENVS, 1)).astype(np.float32)


def rollout(env, keys, acts):
    def body(state, a):
        state = env.step(state, a)
        return state, (state.done, state.info["steps"], state.info["truncation"])

    state = env.reset(keys)
    return jax.lax.scan(body, state, acts)


@pytest.fixture(scope="module")
def rolled():
    base = load_env()
    metrics = make_metrics()
    keys = jax.random.split(jax.random.PRNGKey(0), NUM_ENVS)
    acts = jnp.asarray(actions())
    with jmp.default_promotion():
        wrap = functools.partial(jmp.wrap, metrics=metrics)
        # Called as Brax's ppo.train calls its wrap_env_fn.
        ours = wrap(
            base, episode_length=EPISODE_LENGTH, action_repeat=REPEAT, randomization_fn=None
        )
        theirs = wrapper.wrap_for_brax_training(base, EPISODE_LENGTH, REPEAT)
        state, ours_info = jax.jit(functools.partial(rollout, ours))(keys, acts)
        _, theirs_info = jax.jit(functools.partial(rollout, theirs))(keys, acts)
    report = metrics.to_host(metrics.compute(jmp.metrics_state(state)))
    return {
        "report": report,
        "ours_info": jax.tree.map(np.asarray, ours_info),
        "theirs_info": jax.tree.map(np.asarray, theirs_info),
        "reference": reference_unroll(base, keys, actions()),
    }


def reference_unroll(env, keys, acts):
    """Per-episode values from stepping the unwrapped env sub-step by sub-step, float64."""
    # Playground's auto-reset splits each env's key and resets the env with `[..., 1]` of
    # the split (which indexes the key words, not the two new keys).
    reset_keys = jax.vmap(jax.random.split)(keys)[..., 1]
    with jmp.default_promotion():
        step = jax.jit(jax.vmap(env.step))
        first = jax.jit(jax.vmap(env.reset))(reset_keys)
    state = first
    steps = np.zeros(NUM_ENVS, int)
    running = [[] for _ in range(NUM_ENVS)]
    episodes = []  # (env, [per-sub-step dicts]) in report order: by step, then env index
    for t in range(STEPS):
        for _ in range(REPEAT):
            with jmp.default_promotion():
                state = step(state, jnp.asarray(acts[t]))
            qvel = np.asarray(state.data.qvel, np.float64)
            for e in range(NUM_ENVS):
                running[e].append(
                    {
                        "reward": float(state.reward[e]),
                        "qvel": float(np.sqrt(qvel[e] @ qvel[e])),
                        "pole_speed": abs(float(qvel[e, 1])),
                        "effort": abs(float(acts[t, e, 0])),
                        **{c: float(state.metrics[c][e]) for c in COMPONENTS},
                    }
                )
        steps += REPEAT
        done = steps >= EPISODE_LENGTH
        assert not np.asarray(state.done).any()  # CartpoleBalance only ends at the limit
        for e in np.flatnonzero(done):
            episodes.append(running[e])
            running[e] = []
        steps[done] = 0
        # Done envs restart from their first state (data and obs; info is kept).
        mask = jnp.asarray(done)

        def back(f, x, m=mask):
            return jnp.where(m.reshape((-1,) + (1,) * (x.ndim - 1)), f, x)

        state = state.replace(
            data=jax.tree.map(back, first.data, state.data), obs=back(first.obs, state.obs)
        )
    return episodes


def episode(ep, key, reduce):
    a = np.array([s[key] for s in ep], np.float64)
    return {"sum": a.sum(), "mean": a.mean(), "max": a.max()}[reduce]


def check(report, name, want):
    got = report[f"Episode_Metrics/{name}/window_values"]
    got = got[~np.isnan(got)]
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-6, err_msg=name)
    assert report[f"Episode_Metrics/{name}/count"] == len(want)
    np.testing.assert_allclose(report[f"Episode_Metrics/{name}"], np.mean(want), rtol=2e-5)


@pytest.mark.slow
def test_episode_values_fold_every_sub_step_and_match_a_float64_unroll(rolled):
    report, episodes = rolled["report"], rolled["reference"]
    # 13 env steps, episodes of 5: two finished episodes per env.
    assert len(episodes) == 2 * NUM_ENVS
    check(report, "return", [episode(ep, "reward", "sum") for ep in episodes])
    check(report, "length", [float(len(ep)) for ep in episodes])
    assert {len(ep) for ep in episodes} == {10}
    check(report, "truncated", [1.0] * len(episodes))
    check(report, "qvel", [episode(ep, "qvel", "mean") for ep in episodes])
    check(report, "pole_speed_max", [episode(ep, "pole_speed", "max") for ep in episodes])
    check(report, "effort", [episode(ep, "effort", "mean") for ep in episodes])
    for c in COMPONENTS:
        check(report, c, [episode(ep, c, "sum") for ep in episodes])


@pytest.mark.slow
def test_playground_info_keys_are_those_of_wrap_for_brax_training(rolled):
    for ours, theirs, name in zip(rolled["ours_info"], rolled["theirs_info"], BRAX_INFO):
        np.testing.assert_array_equal(ours, theirs, err_msg=name)


def test_wrap_rejects_what_it_cannot_wrap():
    metrics = jm.Metrics(terms={"return": jmp.episode_return()})
    with pytest.raises(TypeError, match="must be a MuJoCo Playground MjxEnv.*jaxmetrics.brax.wrap"):
        jmp.wrap(object(), metrics)
    env = load_env()
    with pytest.raises(ValueError, match="already wrapped for training.*BraxAutoResetWrapper"):
        jmp.wrap(wrapper.wrap_for_brax_training(env), metrics)
    with pytest.raises(ValueError, match=r"full_reset=True\) is not supported.*full_reset=False"):
        jmp.wrap(env, metrics, full_reset=True)

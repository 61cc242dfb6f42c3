"""jaxmetrics.playground on MuJoCo Playground's CartpoleBalance (MJX, CPU) under lax.scan
with Playground's auto-reset and action_repeat=2, and inside Brax's `ppo.train` with the
env resets between epochs that Playground's configs ask for.

The reference is a hand-written float64 unroll of the unwrapped env: every physics
sub-step is stepped in a Python loop, episodes end at the time limit, and envs that are
done go back to their first state, as Playground's `BraxAutoResetWrapper` does. The
envs in Playground's own `wrap_for_brax_training` are run on the same actions for the
info keys it writes.
"""

import functools
import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.agents.ppo import train as brax_ppo
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


class Leveled(wrapper.Wrapper):
    """An env state with a level in `info` (0 at reset) for `on_reset` to set."""

    def reset(self, rng):
        state = self.env.reset(rng)
        return state.replace(info={**state.info, "level": jnp.zeros((), jnp.int32)})


@pytest.mark.slow
def test_on_reset_levels_survive_playground_s_auto_reset():
    # The rule gives each env that begins an episode the number of episodes finished so
    # far (a live read); Playground's auto-reset, above the wrapper, keeps it in `info`.
    metrics = jm.Metrics(terms={"return": jmp.episode_return()})

    def on_reset(read, state):
        total = read("episodes", "total").astype(jnp.int32)
        return state.replace(
            info={**state.info, "level": jnp.full_like(state.info["level"], total)}
        )

    def levels(env, keys, acts):
        def body(state, a):
            state = env.step(state, a)
            return state, (state.done, state.info["level"])

        return jax.lax.scan(body, env.reset(keys), acts)[1]

    keys = jax.random.split(jax.random.PRNGKey(0), NUM_ENVS)
    with jmp.default_promotion():
        env = jmp.wrap(Leveled(load_env()), metrics, EPISODE_LENGTH, REPEAT, on_reset=on_reset)
        done, level = jax.device_get(jax.jit(functools.partial(levels, env))(keys, actions()))
    want, finished = np.zeros(NUM_ENVS, int), 0
    for t in range(STEPS):
        finished += int(done[t].sum())
        want = np.where(done[t] != 0, finished, want)
        np.testing.assert_array_equal(level[t], want, err_msg=f"step {t}")
    assert finished >= 2 * NUM_ENVS and len(np.unique(level)) >= 3  # 0, then two levels


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


# Brax's PPO, smoke-sized: epochs of 2 training steps of 256 env steps (512 env steps, 32
# steps of the 16-env batch), 2 epochs per evaluation, each followed by an env reset
# (num_resets_per_eval), 4 epochs in all; episodes of 10 env steps, so every epoch ends 3
# episodes per env and leaves one running.
PPO_ENVS, PPO_EPISODE, PPO_RESETS = 16, 10, 2


def _episodes_by(env_step: int, epoch: int) -> int:
    """The episodes all envs ended in the first `env_step` env steps of the training, where
    the trainer resets every env after each `epoch` env steps. CartpoleBalance never
    terminates, so each env ends an episode at every multiple of the time limit of its
    steps since its last reset, and an episode running at a reset never ends."""
    since_reset = ended = 0
    for t in range(1, env_step // PPO_ENVS + 1):
        since_reset += 1
        ended += since_reset % PPO_EPISODE == 0
        if t % (epoch // PPO_ENVS) == 0:
            since_reset = 0
    return ended * PPO_ENVS


@pytest.mark.slow
@pytest.mark.parametrize("report_every", [384, 512])
def test_brax_ppo_env_resets_keep_the_playground_wrapper_s_records(
    brax_ppo_on_this_jax, report_every
):
    # The reset-frame walk knew Brax's Wrapper only, and Playground's BraxAutoResetWrapper
    # (the top of jmp.wrap's stack) is not one: every env reset restarted the wrapper, so
    # Counters/episodes went 48, 48, 48, 48 (384: records stamped 384, 768, 1152, 1536
    # where the envs had run 384, 896, 1408, 1920 env steps), and close() noticed a
    # trainer that does not hand over its state. 512 divides the epoch, 384 does not.
    metrics = jm.Metrics(
        terms={
            "length": jmp.episode_length(stats=("mean", "count")),
            "truncated": jmp.truncation_rate(stats=("mean",)),
        }
    )
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])
    progress: list[int] = []
    with warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")
        with jmp.default_promotion():  # the suite runs strict (conftest)
            brax_ppo.train(
                environment=load_env(),
                num_timesteps=2048,
                episode_length=PPO_EPISODE,
                num_envs=PPO_ENVS,
                batch_size=16,
                num_minibatches=2,
                unroll_length=8,
                num_updates_per_batch=1,
                num_evals=3,
                num_eval_envs=4,
                num_resets_per_eval=PPO_RESETS,
                max_devices_per_host=1,
                wrap_env_fn=functools.partial(
                    jmp.wrap, metrics=metrics, logger=logger, report_every=report_every
                ),
                progress_fn=lambda step, _: progress.append(int(step)),
                seed=0,
            )
        logger.close()

    # Brax's own steps: its evaluations, `PPO_RESETS` epochs apart, and its last step.
    final = progress[-1]
    epoch = (progress[1] - progress[0]) // PPO_RESETS
    assert final // epoch > PPO_RESETS  # the records run across several env resets
    # A report at the first batch step that reaches each period: the record's step is
    # Brax's env step there, up to the last one within the training.
    period = math.ceil(report_every / PPO_ENVS) * PPO_ENVS
    steps = list(range(period, final + 1, period))
    records = [r for r in memory.records if "Counters/episodes" in r.scalars]
    assert [r.step for r in records] == steps
    assert [r.scalars["Counters/env_steps"] for r in records] == steps

    ended = [_episodes_by(s, epoch) for s in steps]
    got = [int(r.scalars["Counters/episodes"]) for r in records]
    assert got == ended
    assert all(a < b for a, b in zip(got, got[1:]))  # counters go on through every reset
    assert [int(r.scalars["Episode_Metrics/length/count"]) for r in records] == [
        b - a for a, b in zip([0, *ended], ended)
    ]
    for r in records:  # every episode ran to the time limit: none ended at a reset
        assert r.scalars["Episode_Metrics/length"] == PPO_EPISODE
        assert r.scalars["Episode_Metrics/truncated"] == 1.0

    # No notice of a restart; only the steps after the last record, where there are any.
    notices = [str(w.message) for w in warned if issubclass(w.category, RuntimeWarning)]
    if final % period == 0:
        assert notices == []
    else:
        (notice,) = notices
        assert (
            f"wrote its last record at env step {steps[-1]:,}: the last "
            f"{final - steps[-1]:,} of the {final:,} env steps" in notice
        ), notice

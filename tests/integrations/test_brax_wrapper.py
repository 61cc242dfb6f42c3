"""jaxmetrics.brax on real Brax envs (mjx backend) rolled out under lax.scan with auto-reset.

References are unrolled in plain Python/numpy float64 from per-step values and dones
recorded from the same rollout (State.metrics and State.reward are not touched by
AutoResetWrapper, so they hold the terminal step's values), or read from Brax's own
EpisodeWrapper run side by side on the same actions.
"""

import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax import envs
from brax.envs.base import State
from brax.envs.inverted_pendulum import InvertedPendulum
from brax.envs.wrappers import training as brax_training
from reference import episode_values

import jaxmetrics as jm
import jaxmetrics.brax as jmb
from jaxmetrics.brax import _terms

NUM_ENVS = 8
STEPS = 60
EPISODE_LENGTH = 25
WINDOW = jm.window(256)
STATS = ("mean", "std", "min", "max", "count", WINDOW)
METRIC_NAMES = ("upright", "effort", "cart_x", "pole_angle", "qd_cart", "qd_pole")

# Per-env policy: a PD controller (gain) plus uniform noise. Envs 0-2 balance and time out,
# the others fall after 4 to ~25 steps: very different episode lengths across envs.
GAIN = np.array([1.0, 1.0, 0.5, 0.5, 0.0, 0.0, -0.5, 0.0], np.float32)
NOISE = np.array([0.0, 0.3, 0.0, 0.5, 1.0, 0.2, 0.0, 0.0], np.float32)


class Pendulum(InvertedPendulum):
    """inverted_pendulum whose reward has components, with physics readings in State.metrics."""

    def reset(self, rng):
        state = super().reset(rng)
        zero = jnp.zeros((), jnp.float32)
        return state.replace(metrics={k: zero for k in METRIC_NAMES})

    def step(self, state, action):
        state = super().step(state, action)
        q, qd = state.pipeline_state.q, state.pipeline_state.qd
        upright = jnp.cos(q[1])
        effort = -0.1 * jnp.sum(action * action)
        metrics = dict(
            upright=upright,
            effort=effort,
            cart_x=q[0],
            pole_angle=q[1],
            qd_cart=qd[0],
            qd_pole=qd[1],
        )
        return state.replace(reward=upright + effort, metrics=metrics)


def policy(obs, key):
    pd = 2.0 * obs[:, 1:2] + 0.3 * obs[:, 3:4] + 0.1 * obs[:, 0:1] + 0.1 * obs[:, 2:3]
    noise = jax.random.uniform(key, (NUM_ENVS, 1), jnp.float32, -1.0, 1.0)
    return jnp.clip(jnp.asarray(GAIN)[:, None] * pd + jnp.asarray(NOISE)[:, None] * noise, -1, 1)


def make_metrics():
    terms = {
        "return": jmb.episode_return(stats=STATS),
        "length": jmb.episode_length(stats=STATS),
        "terminated": jmb.termination_rate(stats=STATS),
        "truncated": jmb.truncation_rate(stats=STATS),
        "joint_vel": jmb.joint_velocity(stats=STATS),
        "pole_speed_max": jmb.joint_velocity([1], ord=np.inf, reduce="max", stats=STATS),
        "effort_norm": jmb.control_effort(stats=STATS),
        "balanced": jmb.success_rate(
            lambda t: jnp.abs(t.state.obs[:, 1]) < 0.05, reduce="max", stats=STATS
        ),
        # Terminal state, not the auto-reset one; and the pre-step state.
        "final_angle": jm.Term(lambda t: t.state.obs[:, 1], reduce="last", stats=STATS),
        "angle_step_max": jm.Term(
            lambda t: jnp.abs(t.state.obs[:, 1] - t.prev_state.obs[:, 1]), reduce="max", stats=STATS
        ),
        **jmb.state_metrics({"upright": "sum", "effort": "sum", "cart_x": "last"}, stats=STATS),
        "cart_x_std": jmb.state_metrics({"cart_x": "std"}, stats=STATS)["cart_x"],
        "cart_x_min": jmb.state_metrics({"cart_x": "min"}, stats=STATS)["cart_x"],
        "upright_per_s": jmb.state_metrics(["upright"], per_second=True, stats=STATS)["upright"],
        # Grouped by the side of the track the cart is on when the episode ends.
        "return_by_side": jm.Term(
            lambda t: t.state.reward,
            reduce="sum",
            stats=STATS,
            groups=jm.groups(lambda t: t.state.metrics["cart_x"] > 0, ("left", "right")),
        ),
    }
    return jm.Metrics(terms=terms)


def reported(report, name):
    values = report[f"Episode_Metrics/{name}/window_values"]
    return values[~np.isnan(values)]


def check_report(report, name, expected):
    got = reported(report, name)
    assert got.shape == expected.shape, name
    np.testing.assert_allclose(got, expected, rtol=2e-5, atol=2e-6, err_msg=name)
    tag = f"Episode_Metrics/{name}"
    assert report[f"{tag}/count"] == len(expected)
    np.testing.assert_allclose(report[tag], expected.mean(), rtol=2e-5, atol=2e-6)
    np.testing.assert_allclose(report[f"{tag}/std"], expected.std(), rtol=1e-4, atol=2e-6)
    np.testing.assert_allclose(report[f"{tag}/min"], expected.min(), rtol=2e-5, atol=2e-6)
    np.testing.assert_allclose(report[f"{tag}/max"], expected.max(), rtol=2e-5, atol=2e-6)


BRAX_KEYS = ("steps", "truncation", "episode_done")


def run_side_by_side(backend, steps):
    """One rollout of our stack and Brax's `training.wrap` side by side, same actions."""
    base = Pendulum(backend=backend)
    metrics = make_metrics()
    ours = jmb.wrap(base, metrics, episode_length=EPISODE_LENGTH)
    theirs = brax_training.wrap(base, episode_length=EPISODE_LENGTH)

    def record(s):
        return dict(
            obs=s.obs,
            reward=s.reward,
            done=s.done,
            metrics=s.metrics,
            episode_metrics=s.info["episode_metrics"],
            **{k: s.info[k] for k in BRAX_KEYS},
        )

    def run(reset_keys, step_keys):
        s_ours = ours.reset(reset_keys)
        with jmb.default_promotion():
            s_theirs = theirs.reset(reset_keys)

        def body(carry, key):
            s_ours, s_theirs = carry
            action = policy(s_ours.obs, key)
            s_ours = ours.step(s_ours, action)
            with jmb.default_promotion():
                s_theirs = theirs.step(s_theirs, action)
            return (s_ours, s_theirs), (record(s_ours), record(s_theirs), action)

        (s_ours, _), recs = jax.lax.scan(body, (s_ours, s_theirs), step_keys)
        return s_ours, s_ours.obs, recs

    keys = jax.random.split(jax.random.PRNGKey(0), NUM_ENVS)
    step_keys = jax.random.split(jax.random.PRNGKey(1), steps)
    reset_obs = jax.jit(ours.reset)(keys).obs
    final, _, (ours_rec, theirs_rec, actions) = jax.jit(run)(keys, step_keys)
    report = metrics.to_host(metrics.compute(jmb.metrics_state(final)))
    ours_rec, theirs_rec = jax.device_get((ours_rec, theirs_rec))
    return dict(
        metrics=metrics,
        final=final,
        report=report,
        ours=ours_rec,
        theirs=theirs_rec,
        actions=np.asarray(actions),
        reset_obs=np.asarray(reset_obs),
        dt=float(base.dt),
    )


@pytest.fixture(scope="module")
def pendulum():
    return run_side_by_side("mjx", STEPS)


def check_against_unroll(pendulum):
    r = pendulum["ours"]
    m = r["metrics"]
    done = r["done"] != 0
    trunc = r["truncation"] != 0
    # The outer obs after step t is the obs fed to step t+1: the pre-step state's.
    prev_angle = np.concatenate([pendulum["reset_obs"][None, :, 1], r["obs"][:-1, :, 1]])
    qd = np.stack([m["qd_cart"], m["qd_pole"]], -1).astype(np.float64)
    cases = {
        "return": (r["reward"], "sum"),
        "length": (np.ones_like(r["reward"]), "sum"),
        "terminated": (done & ~trunc, "last"),
        "truncated": (trunc, "last"),
        "joint_vel": (np.linalg.norm(qd, axis=-1), "mean"),
        "pole_speed_max": (np.abs(m["qd_pole"]), "max"),
        "effort_norm": (np.abs(pendulum["actions"][..., 0]), "mean"),
        "balanced": (np.abs(m["pole_angle"]) < 0.05, "max"),
        "final_angle": (m["pole_angle"], "last"),
        "angle_step_max": (np.abs(m["pole_angle"] - prev_angle), "max"),
        "upright": (m["upright"], "sum"),
        "effort": (m["effort"], "sum"),
        "cart_x": (m["cart_x"], "last"),
        "cart_x_std": (m["cart_x"], "std"),
        "cart_x_min": (m["cart_x"], "min"),
        "upright_per_s": (m["upright"] / (EPISODE_LENGTH * pendulum["dt"]), "sum"),
    }
    report = pendulum["report"]
    for name, (values, reduce) in cases.items():
        check_report(report, name, episode_values(values, done, reduce))
    # An episode's group is the cart's side on its last step; episodes in report order.
    returns = episode_values(r["reward"], done, "sum")
    right = m["cart_x"][done] > 0  # step-major, then env index: report order
    check_report(report, "return_by_side", returns)
    check_report(report, "return_by_side/right", returns[right])
    check_report(report, "return_by_side/left", returns[~right])
    assert right.any() and (~right).any()
    assert report["Counters/episodes"] == done.sum()
    assert report["Counters/env_steps"] == done.size


def check_against_brax(pendulum):
    ours, theirs = pendulum["ours"], pendulum["theirs"]
    np.testing.assert_array_equal(ours["done"], theirs["done"])
    # Two programs compiled apart (ours, and Brax's EpisodeWrapper) may fuse the physics
    # differently: float32 rounding grows along the unstable pendulum's trajectory to a few
    # 1e-6 (XLA:CPU's elemental emitters, JAX 0.9.1 and MuJoCo 3.2: 6e-6 on the
    # observations, 2.5e-5 on the sum of an episode's pole velocities). A wrapper that
    # changed the trajectory, or dropped a step, moves them by orders of magnitude more.
    np.testing.assert_allclose(ours["obs"], theirs["obs"], rtol=1e-5, atol=1e-4)
    done = theirs["done"] != 0
    steps, envs_ = np.nonzero(done)  # step-major, then ascending env index: report order
    brax_sums = theirs["episode_metrics"]
    for name, brax_name in [
        ("return", "sum_reward"),
        ("length", "length"),
        ("upright", "upright"),
        ("effort", "effort"),
    ]:
        expected = brax_sums[brax_name][steps, envs_].astype(np.float64)
        np.testing.assert_allclose(reported(pendulum["report"], name), expected, rtol=2e-5)


@pytest.mark.slow
def test_per_episode_values_match_python_unroll(pendulum):
    check_against_unroll(pendulum)


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["positional"])
def test_other_backends_match_unroll_and_brax(backend):
    pendulum = run_side_by_side(backend, 30)
    assert (pendulum["ours"]["done"] != 0).sum() >= NUM_ENVS
    check_against_unroll(pendulum)
    check_against_brax(pendulum)


@pytest.mark.slow
def test_terms_see_the_terminal_state_not_the_auto_reset_one(pendulum):
    r = pendulum["ours"]
    done = r["done"] != 0
    terminated = done & (r["truncation"] == 0)
    # AutoResetWrapper has put the reset obs (|angle| <= 0.01) into the outer state...
    assert np.all(np.abs(r["obs"][..., 1][done]) <= 0.011)
    # ...while the terms saw the terminal state: a fallen pole on terminated episodes.
    final = reported(pendulum["report"], "final_angle")
    ended_terminated = episode_values(terminated, done, "last").astype(bool)
    assert ended_terminated.sum() >= 10
    assert np.all(np.abs(final[ended_terminated]) > 0.2)


@pytest.mark.slow
def test_episode_sums_equal_brax_episode_wrapper(pendulum):
    check_against_brax(pendulum)


@pytest.mark.slow
def test_brax_info_keys_are_a_drop_in_for_episode_wrapper(pendulum):
    ours, theirs = pendulum["ours"], pendulum["theirs"]
    for key in (*BRAX_KEYS, "reward"):
        np.testing.assert_allclose(ours[key], theirs[key], rtol=1e-6, err_msg=key)
        assert ours[key].dtype == theirs[key].dtype, key
    assert set(ours["episode_metrics"]) == set(theirs["episode_metrics"])
    for key, value in theirs["episode_metrics"].items():
        # Sums over the trajectory (check_against_brax says why an absolute bound too).
        np.testing.assert_allclose(
            ours["episode_metrics"][key], value, rtol=1e-5, atol=1e-4, err_msg=key
        )


@pytest.mark.slow
def test_episode_lengths_differ_widely_across_envs(pendulum):
    r = pendulum["ours"]
    done = r["done"] != 0
    trunc = r["truncation"] != 0
    lengths = episode_values(np.ones(done.shape), done, "sum")
    truncated = episode_values(trunc, done, "last").astype(bool)
    # Both ways of ending occur, within and across envs, with lengths from a few steps to
    # the limit; every truncated episode has exactly the limit's length.
    assert truncated.sum() >= 4 and (~truncated).sum() >= 10
    assert np.all(lengths[truncated] == EPISODE_LENGTH)
    assert lengths[~truncated].min() <= 6
    per_env = [set(np.diff(np.flatnonzero(np.r_[True, done[:, e]]))) for e in range(NUM_ENVS)]
    assert len(set().union(*per_env)) >= 5
    report = pendulum["report"]
    assert report["Episode_Metrics/truncated"] == pytest.approx(truncated.mean(), rel=1e-6)
    assert report["Episode_Metrics/terminated"] == pytest.approx(1 - truncated.mean(), rel=1e-6)
    assert report["Episode_Metrics/length/max"] == EPISODE_LENGTH


@pytest.mark.slow
def test_replace_metrics_state_starts_a_new_period(pendulum):
    metrics, final = pendulum["metrics"], pendulum["final"]
    ms = jmb.metrics_state(final)
    fresh = jmb.replace_metrics_state(final, metrics.reset_period(ms))
    report = metrics.to_host(metrics.compute(jmb.metrics_state(fresh)))
    assert report["Episode_Metrics/return/count"] == 0
    assert np.isnan(report["Episode_Metrics/return"])
    # Windows and counters carry on; the env part of the state is untouched.
    np.testing.assert_array_equal(
        report["Episode_Metrics/return/window_values"],
        pendulum["report"]["Episode_Metrics/return/window_values"],
    )
    assert report["Counters/env_steps"] == STEPS * NUM_ENVS
    np.testing.assert_array_equal(fresh.obs, final.obs)


# ---------------------------------------------------------------- action_repeat > 1

REPEAT = 3
REPEAT_LENGTH = 24  # sub-steps: 8 env steps
REPEAT_STEPS = 30


def randomize_damping(sys):
    """Brax's domain-randomization convention: a vectorized system and its vmap in_axes."""
    scale = jnp.linspace(0.5, 3.0, NUM_ENVS, dtype=jnp.float32)[:, None]
    in_axes = jax.tree.map(lambda x: None, sys).tree_replace({"dof_damping": 0})
    return sys.tree_replace({"dof_damping": jnp.asarray(sys.dof_damping)[None] * scale}), in_axes


@pytest.fixture(scope="module")
def repeated():
    """Our stack with action_repeat=3 and per-env randomized damping, and a hand-written
    sub-step loop over Brax's DomainRandomizationVmapWrapper as the reference."""
    base = Pendulum(backend="mjx")
    metrics = jm.Metrics(
        terms={
            "return": jmb.episode_return(stats=STATS),
            "length": jmb.episode_length(stats=STATS),
            "joint_vel": jmb.joint_velocity(stats=STATS),
            "pole_speed_max": jmb.joint_velocity([1], ord=np.inf, reduce="max", stats=STATS),
            "truncated": jmb.truncation_rate(stats=STATS),
            **jmb.state_metrics({"upright": "sum", "cart_x": "last"}, stats=STATS),
            "discounted": jm.Term(lambda t: t.state.reward, reduce=jm.discounted(0.9), stats=STATS),
        }
    )
    ours = jmb.wrap(
        base,
        metrics,
        episode_length=REPEAT_LENGTH,
        action_repeat=REPEAT,
        randomization_fn=randomize_damping,
    )
    batched = brax_training.DomainRandomizationVmapWrapper(base, randomize_damping)

    def run(reset_keys, step_keys):
        s_ours = ours.reset(reset_keys)
        with jmb.default_promotion():
            first = batched.reset(reset_keys)

        def body(carry, key):
            s_ours, s_ref, steps = carry
            action = policy(s_ours.obs, key)
            s_ours = ours.step(s_ours, action)
            subs = []
            with jmb.default_promotion():
                for _ in range(REPEAT):
                    s_ref = batched.step(s_ref, action)
                    subs.append(dict(reward=s_ref.reward, metrics=s_ref.metrics, done=s_ref.done))
            steps = steps + REPEAT
            done = (subs[-1]["done"] != 0) | (steps >= REPEAT_LENGTH)
            trunc = (steps >= REPEAT_LENGTH) & (subs[-1]["done"] == 0)

            def reset_where(a, b):
                return jnp.where(done.reshape(done.shape + (1,) * (a.ndim - 1)), a, b)

            s_ref = s_ref.replace(
                pipeline_state=jax.tree.map(
                    reset_where, first.pipeline_state, s_ref.pipeline_state
                ),
                obs=reset_where(first.obs, s_ref.obs),
            )
            steps = jnp.where(done, 0, steps)
            rec = dict(
                subs=subs,
                done=done,
                truncation=trunc,
                ours_done=s_ours.done,
                ours_obs=s_ours.obs,
                ref_obs=s_ref.obs,
                brax_upright=s_ours.info["episode_metrics"]["upright"],
            )
            return (s_ours, s_ref, steps), rec

        zeros = jnp.zeros((NUM_ENVS,), jnp.int32)
        (s_ours, _, _), rec = jax.lax.scan(body, (s_ours, first, zeros), step_keys)
        return metrics.compute(jmb.metrics_state(s_ours)), rec

    keys = jax.random.split(jax.random.PRNGKey(2), NUM_ENVS)
    step_keys = jax.random.split(jax.random.PRNGKey(3), REPEAT_STEPS)
    report, rec = jax.jit(run)(keys, step_keys)
    return metrics.to_host(report), jax.device_get(rec)


@pytest.mark.slow
def test_action_repeat_folds_every_substep(repeated):
    report, rec = repeated
    np.testing.assert_array_equal(rec["ours_done"] != 0, rec["done"])
    np.testing.assert_allclose(rec["ours_obs"], rec["ref_obs"], rtol=1e-6, atol=1e-6)
    done = rec["done"]
    assert done.sum() >= 8 and rec["truncation"].sum() >= 2 and (done & ~rec["truncation"]).any()
    subs = rec["subs"]

    def flat(get):  # [steps, repeat, envs] -> [steps * repeat, envs], sub-steps in order
        return np.stack([get(s) for s in subs], axis=1).reshape(-1, NUM_ENVS)

    sub_done = np.zeros((REPEAT_STEPS, REPEAT, NUM_ENVS), bool)
    sub_done[:, -1] = done
    sub_done = sub_done.reshape(-1, NUM_ENVS)
    qd = np.stack(
        [flat(lambda s: s["metrics"]["qd_cart"]), flat(lambda s: s["metrics"]["qd_pole"])], -1
    )
    cases = {
        "return": (flat(lambda s: s["reward"]), "sum"),
        "length": (np.ones(sub_done.shape), "sum"),
        # Mean over all sub-steps: the per-env-step mean over sub-steps, averaged.
        "joint_vel": (np.linalg.norm(qd.astype(np.float64), axis=-1), "mean"),
        "pole_speed_max": (np.abs(flat(lambda s: s["metrics"]["qd_pole"])), "max"),
        "upright": (flat(lambda s: s["metrics"]["upright"]), "sum"),
        "cart_x": (flat(lambda s: s["metrics"]["cart_x"]), "last"),
        "truncated": (np.repeat(rec["truncation"], REPEAT, axis=0) & sub_done, "last"),
    }
    for name, (values, reduce) in cases.items():
        check_report(report, name, episode_values(values, sub_done, reduce))
    # Every sub-step is a step of the discount: t = env step * REPEAT + sub-step.
    rewards = flat(lambda s: s["reward"]).astype(np.float64)
    discounted, total, t = [], np.zeros(NUM_ENVS), np.zeros(NUM_ENVS, int)
    for k in range(rewards.shape[0]):
        total += 0.9**t * rewards[k]
        t += 1
        for e in np.flatnonzero(sub_done[k]):
            discounted.append(total[e])
            total[e], t[e] = 0.0, 0
    check_report(report, "discounted", np.asarray(discounted))
    assert report["Counters/env_steps"] == REPEAT_STEPS * REPEAT * NUM_ENVS
    # Env-step view of the same mean: average each env step's sub-step mean.
    step_means = np.linalg.norm(qd.astype(np.float64), axis=-1).reshape(REPEAT_STEPS, REPEAT, -1)
    expected = episode_values(step_means.mean(axis=1), done, "mean")
    np.testing.assert_allclose(reported(report, "joint_vel"), expected, rtol=2e-5)


@pytest.mark.slow
def test_action_repeat_brax_keys_keep_only_the_last_substep_metrics(repeated):
    # Brax's EpisodeWrapper semantics (google/brax#610), reproduced in info['episode_metrics']
    # for drop-in compatibility; the jaxmetrics term counts every sub-step.
    report, rec = repeated
    done = rec["done"]
    last_sub = rec["subs"][-1]["metrics"]["upright"]
    steps, envs_ = np.nonzero(done)
    expected_brax = episode_values(last_sub, done, "sum")
    np.testing.assert_allclose(rec["brax_upright"][steps, envs_], expected_brax, rtol=2e-5)
    assert np.all(reported(report, "upright") > expected_brax * (REPEAT - 0.5))


# ---------------------------------------------------------------- ant, once


@pytest.mark.slow
def test_ant_reward_components_and_return_match_unroll():
    num_envs, steps, length = 4, 24, 10
    base = envs.get_environment("ant", backend="mjx")
    components = ["reward_forward", "reward_survive", "reward_ctrl", "reward_contact"]
    metrics = jm.Metrics(
        terms={
            "return": jmb.episode_return(stats=STATS),
            "length": jmb.episode_length(stats=STATS),
            **jmb.state_metrics(components, stats=STATS),
            **jmb.state_metrics({"x_position": "last", "x_velocity": "mean"}, stats=STATS),
        }
    )
    env = jmb.wrap(base, metrics, episode_length=length)

    def run(key):
        state = env.reset(jax.random.split(key, num_envs))

        def body(s, k):
            a = jax.random.uniform(k, (num_envs, base.action_size), jnp.float32, -1, 1)
            s = env.step(s, a)
            em = s.info["episode_metrics"]
            return s, dict(
                reward=s.reward, done=s.done, metrics=s.metrics, sum_reward=em["sum_reward"]
            )

        state, rec = jax.lax.scan(body, state, jax.random.split(key, steps))
        return metrics.compute(jmb.metrics_state(state)), rec

    report, rec = jax.jit(run)(jax.random.PRNGKey(4))
    report, rec = metrics.to_host(report), jax.device_get(rec)
    done = rec["done"] != 0
    assert done.sum() >= num_envs * 2
    m = rec["metrics"]
    for name in components:
        check_report(report, name, episode_values(m[name], done, "sum"))
    check_report(report, "return", episode_values(rec["reward"], done, "sum"))
    check_report(report, "x_position", episode_values(m["x_position"], done, "last"))
    check_report(report, "x_velocity", episode_values(m["x_velocity"], done, "mean"))
    steps_, envs_ = np.nonzero(done)
    np.testing.assert_allclose(
        reported(report, "return"), rec["sum_reward"][steps_, envs_], rtol=2e-5, atol=1e-5
    )


# ---------------------------------------------------------------- errors


def test_wrapper_order_is_enforced():
    metrics = jm.Metrics(terms={"return": jmb.episode_return()})
    base = Pendulum(backend="mjx")
    episodic = brax_training.EpisodeWrapper(brax_training.VmapWrapper(base), 10, 1)
    with pytest.raises(ValueError, match="replaces EpisodeWrapper"):
        jmb.MetricsWrapper(episodic, metrics, episode_length=10)
    with pytest.raises(ValueError, match="replaces EpisodeWrapper"):
        jmb.MetricsWrapper(brax_training.wrap(base, 10), metrics, episode_length=10)
    with pytest.raises(ValueError, match="already in this env stack"):
        jmb.MetricsWrapper(jmb.wrap(base, metrics).env, metrics, episode_length=10)


def test_unbatched_env_is_rejected_at_reset():
    metrics = jm.Metrics(terms={"return": jmb.episode_return()})
    env = jmb.MetricsWrapper(Pendulum(backend="mjx"), metrics, episode_length=10)
    with pytest.raises(ValueError, match="needs a batched env.*VmapWrapper"):
        jax.eval_shape(env.reset, jax.random.PRNGKey(0))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(episode_length=0), "episode_length=...\\) must be a positive int"),
        (dict(episode_length=10, action_repeat=True), "action_repeat=...\\) must be"),
        (dict(episode_length=10.0), "episode_length=...\\) must be a positive int"),
    ],
)
def test_bad_wrapper_config(kwargs, match):
    metrics = jm.Metrics(terms={"return": jmb.episode_return()})
    with pytest.raises(ValueError, match=match):
        jmb.MetricsWrapper(brax_training.VmapWrapper(Pendulum(backend="mjx")), metrics, **kwargs)


def test_metrics_must_be_a_spec():
    with pytest.raises(TypeError, match="must be a jaxmetrics.Metrics"):
        jmb.wrap(Pendulum(backend="mjx"), {"return": jmb.episode_return()})


def test_metrics_state_of_an_unwrapped_state():
    state = State(None, jnp.zeros((2, 1)), jnp.zeros(2), jnp.zeros(2))
    with pytest.raises(ValueError, match="jaxmetrics.brax.wrap"):
        jmb.metrics_state(state)


def fake_transition(metrics):
    zeros = jnp.zeros((2,), jnp.float32)
    state = State(None, jnp.zeros((2, 1)), zeros, zeros, metrics)
    no = jnp.zeros((2,), bool)
    return jmb.Transition(state, state, jnp.zeros((2, 1)), no, no, no, 0.5, 10)


def test_state_metrics_names_and_per_second():
    term = jmb.state_metrics(["a"], per_second=True)["a"]
    t = fake_transition({"a": jnp.array([5.0, 10.0], jnp.float32)})
    # Isaac Lab style: divided by the max episode length in seconds (10 steps x 0.5 s).
    np.testing.assert_allclose(term.fn(t, **term.params), [1.0, 2.0])
    term = jmb.state_metrics(["b"])["b"]
    with pytest.raises(ValueError, match=r"'b' is not in State.metrics; this env has \['a'\]"):
        term.fn(t, **term.params)
    with pytest.raises(ValueError, match="per_second=True.*'x' has reduction 'mean'"):
        jmb.state_metrics({"x": "mean"}, per_second=True)
    with pytest.raises(ValueError, match="unknown episode reduction 'avg'"):
        jmb.state_metrics(["x"], reduce="avg")
    with pytest.raises(TypeError, match="got the string"):
        jmb.state_metrics("reward_forward")


def test_helper_argument_checks():
    with pytest.raises(ValueError, match="ord=3"):
        jmb.joint_velocity(ord=3)
    with pytest.raises(ValueError, match="indices must be"):
        jmb.control_effort(indices=[[0, 1]])
    with pytest.raises(ValueError, match="success_rate\\(reduce='sum'\\)"):
        jmb.success_rate(lambda t: t.done, reduce="sum")
    flag = jmb.success_rate(lambda t: t.state.reward)
    with pytest.raises(TypeError, match="return a bool array"):
        flag.fn(fake_transition({}))
    norm = _terms.norm(lambda t: t.state.reward)
    with pytest.raises(ValueError, match=r"must be \[num_envs, D\]"):
        norm.fn(fake_transition({}))


def test_step_returns_the_types_reset_gives_so_host_loops_compile_once():
    # inverted_pendulum builds `done` with Python scalars: weakly typed in step, not in
    # reset. A jitted host loop feeding step's output back would compile twice.
    metrics = jm.Metrics(terms={"return": jmb.episode_return()})
    env = jmb.wrap(envs.get_environment("inverted_pendulum", backend="mjx"), metrics, 10)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    reset = jax.eval_shape(env.reset, keys)
    stepped = jax.eval_shape(env.step, reset, jax.ShapeDtypeStruct((2, 1), jnp.float32))
    assert jax.tree.structure(stepped) == jax.tree.structure(reset)
    for path, (a, b) in zip(
        jax.tree_util.tree_flatten_with_path(reset)[0],
        zip(jax.tree.leaves(reset), jax.tree.leaves(stepped)),
    ):
        assert (a.shape, a.dtype, a.weak_type) == (b.shape, b.dtype, b.weak_type), path[0]


_QUIET = """
import sys, warnings
import jaxmetrics as jm
stdout = sys.stdout
before = list(warnings.filters)
import jaxmetrics.brax as jmb
from brax import envs
# Importing jaxmetrics.brax changes nothing: no filter of Brax's (numpy and scipy add
# their own when imported), no blanket "ignore", the same standard output.
added = [f for f in warnings.filters if f not in before]
assert not [f for f in added if f[1] is not None and "brax" in f[1].pattern.lower()], added
assert not [f for f in added if f[0] == "ignore" and f[1] is None], added
assert sys.stdout is stdout
filters = list(warnings.filters)
with jmb.quiet_upstream():
    print("Failed to import warp: no module named 'warp'")
    print("kept: printed inside the block")
    print("Failed to import mujoco_warp: no module named 'mujoco_warp'")
    envs.get_environment("inverted_pendulum", backend="mjx")
    warnings.warn_explicit(
        "Brax System, piplines and environments are not actively being maintained",
        UserWarning, "elsewhere.py", 1, module="elsewhere",
    )
assert warnings.filters == filters and sys.stdout is stdout
print("after the block")
envs.get_environment("inverted_pendulum", backend="mjx")  # warns again: the filter is gone
"""


def test_quiet_upstream_hides_the_two_known_notices_inside_its_block_and_nothing_else():
    root = pathlib.Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-W", "default", "-c", _QUIET],
        capture_output=True,
        text=True,
        cwd=root,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == ["kept: printed inside the block", "after the block"]
    # Brax's own warning is hidden in the block only; the same text from elsewhere, and
    # other warnings (jaxopt's deprecation, shown under -W default), still get through.
    assert out.stderr.count("not actively being maintained") == 2
    assert "elsewhere.py:1: UserWarning" in out.stderr
    assert out.stderr.count("brax/io/mjcf.py") == 1, out.stderr
    assert "JAXopt is no longer maintained" in out.stderr


@pytest.mark.parametrize(("devices", "history"), [(1, False), (2, True), (None, True)])
def test_ema_history_is_kept_only_where_devices_may_merge(devices, history):
    # A wrapper whose statistics are used inside the trainer (here read by on_reset) keeps
    # each EMA's newest values for an exact merge over devices, a scatter on every step.
    # Under a pmap of one device nothing merges, so it keeps none; under 2 it does; reset
    # under no axis (as Brax's SAC pmaps its reset) it does where the process has several
    # devices (the suite has 8).
    metrics = jm.Metrics(terms={"return": jmb.episode_return(stats=("mean", jm.ema(0.1)))})
    base = envs.get_environment("inverted_pendulum", backend="spring")
    env = jmb.wrap(base, metrics, episode_length=10, on_reset=lambda read, s: s)
    with jmb.default_promotion():
        if devices is None:
            state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(0), 4))
        else:
            keys = jax.random.split(jax.random.PRNGKey(0), devices * 4).reshape(devices, 4, -1)
            reset = jax.pmap(env.reset, axis_name="i", devices=jax.devices()[:devices])
            state = reset(keys)
    rings = state.info["jaxmetrics"].finished.ema_rings
    assert rings and all((r.data.size > 0) == history for r in rings)

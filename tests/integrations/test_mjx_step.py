"""jaxmetrics.wrap_step on a raw MJX loop: a small inline MJCF model stepped with mjx.step.

The reference is unrolled in plain Python/numpy float64 from the per-step values and dones
recorded from the same rollout.
"""

import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from reference import episode_values

import jaxmetrics as jm
import jaxmetrics.brax as jmb

# An inverted pole on a hinge with a motor: it falls unless pushed back.
XML = """
<mujoco>
  <option timestep="0.02"/>
  <worldbody>
    <body>
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0 0 0.5" size="0.05" mass="1"/>
    </body>
  </worldbody>
  <actuator><motor joint="hinge" gear="1" ctrlrange="-2 2"/></actuator>
</mujoco>
"""
NUM_ENVS = 8
STEPS = 50
TIME_LIMIT = 0.5  # seconds: 25 steps
FALLEN = 0.5  # radians
STATS = ("mean", "std", "min", "max", "count", jm.window(128))


def make_step(model):
    def step(data, action):
        # mjx's internals rely on JAX's default promotion (conftest makes it strict).
        with jmb.default_promotion():
            data = jax.vmap(mjx.step, in_axes=(None, 0))(model, data.replace(ctrl=action))
        angle = data.qpos[:, 0]
        reward = jnp.cos(angle) - 0.1 * action[:, 0] * action[:, 0]
        done = (jnp.abs(angle) > FALLEN) | (data.time >= TIME_LIMIT - 1e-4)
        return data, data.qpos, reward, done

    return step


@pytest.fixture(scope="module")
def rollout():
    model = mjx.put_model(mujoco.MjModel.from_xml_string(XML))
    metrics = jm.Metrics(
        terms={
            "return": jm.Term(lambda t: t.reward, reduce="sum", stats=STATS),
            "length": jm.Term(
                lambda t: jnp.ones(t.done.shape, jnp.int32), reduce="sum", stats=STATS
            ),
            "speed": jm.Term(lambda t: jnp.abs(t.carry.qvel[:, 0]), stats=STATS),
            "speed_max": jm.Term(lambda t: jnp.abs(t.carry.qvel[:, 0]), reduce="max", stats=STATS),
            "final_angle": jm.Term(lambda t: t.carry.qpos[:, 0], reduce="last", stats=STATS),
            "timed_out": jm.Term(
                lambda t: t.carry.time >= TIME_LIMIT - 1e-4, reduce="last", stats=STATS
            ),
            "angle_step": jm.Term(
                lambda t: jnp.abs(t.carry.qpos[:, 0] - t.prev_carry.qpos[:, 0]),
                reduce="max",
                stats=STATS,
            ),
            "effort": jm.Term(lambda t: jnp.abs(t.action[:, 0]), stats=STATS),
        }
    )
    wrapped = jm.wrap_step(make_step(model), metrics)
    # Start angles from -0.2 to 0.2 rad, and a per-env push: some fall fast, some hold
    # until the time limit.
    start = jnp.linspace(-0.2, 0.2, NUM_ENVS, dtype=jnp.float32)
    gain = jnp.array([3.0, 3.0, 3.0, -0.5, -1.0, 1.0, 0.5, -0.2], jnp.float32)

    def run(key):
        data0 = jax.vmap(lambda q: mjx.make_data(model).replace(qpos=q[None]))(start)

        def body(carry, k):
            data, mstate = carry
            noise = jax.random.uniform(k, (NUM_ENVS,), jnp.float32, -0.3, 0.3)
            action = jnp.clip(gain * (-5.0 * data.qpos[:, 0] - data.qvel[:, 0]) + noise, -2, 2)
            (data, mstate), obs, reward, done = wrapped((data, mstate), action[:, None])
            rec = dict(
                reward=reward,
                done=done,
                qpos=data.qpos[:, 0],
                qvel=data.qvel[:, 0],
                time=data.time,
                action=action,
                obs=obs,
            )
            # Auto-reset after the wrapped step, so terms saw the terminal state.
            data = jax.tree.map(
                lambda a, b: jnp.where(done.reshape(done.shape + (1,) * (a.ndim - 1)), a, b),
                data0,
                data,
            )
            return (data, mstate), rec

        init = (data0, metrics.init(NUM_ENVS))
        (_, mstate), rec = jax.lax.scan(body, init, jax.random.split(key, STEPS))
        return metrics.compute(mstate), rec, data0.qpos[:, 0]

    report, rec, start_angle = jax.jit(run)(jax.random.PRNGKey(0))
    return metrics.to_host(report), jax.device_get(rec), np.asarray(start_angle)


@pytest.mark.slow
def test_raw_mjx_loop_matches_python_unroll(rollout):
    report, rec, start_angle = rollout
    done = rec["done"]
    # The pre-step angle: the previous post-step one, or the start angle after a reset.
    prev = np.concatenate([start_angle[None], rec["qpos"][:-1]])
    prev = np.where(np.concatenate([np.ones((1, NUM_ENVS), bool), done[:-1]]), start_angle, prev)
    timed_out = rec["time"] >= TIME_LIMIT - 1e-4
    cases = {
        "return": (rec["reward"], "sum"),
        "length": (np.ones(done.shape), "sum"),
        "speed": (np.abs(rec["qvel"]), "mean"),
        "speed_max": (np.abs(rec["qvel"]), "max"),
        "final_angle": (rec["qpos"], "last"),
        "timed_out": (timed_out, "last"),
        "angle_step": (np.abs(rec["qpos"] - prev), "max"),
        "effort": (np.abs(rec["action"]), "mean"),
    }
    for name, (values, reduce) in cases.items():
        expected = episode_values(values, done, reduce)
        got = report[f"Episode_Metrics/{name}/window_values"]
        got = got[~np.isnan(got)]
        np.testing.assert_allclose(got, expected, rtol=2e-5, atol=2e-6, err_msg=name)
        assert report[f"Episode_Metrics/{name}/count"] == len(expected)
        np.testing.assert_allclose(report[f"Episode_Metrics/{name}"], expected.mean(), rtol=2e-5)
    assert report["Counters/env_steps"] == STEPS * NUM_ENVS
    assert report["Counters/episodes"] == done.sum()
    np.testing.assert_array_equal(rec["obs"][..., 0], rec["qpos"])


@pytest.mark.slow
def test_raw_mjx_episodes_end_both_ways_with_varied_lengths(rollout):
    report, rec, _ = rollout
    done = rec["done"]
    timed_out = episode_values(rec["time"] >= TIME_LIMIT - 1e-4, done, "last").astype(bool)
    fell = episode_values(np.abs(rec["qpos"]) > FALLEN, done, "last").astype(bool)
    lengths = episode_values(np.ones(done.shape), done, "sum")
    assert timed_out.sum() >= 2 and fell.sum() >= 4
    assert np.all(timed_out | fell)
    assert lengths.max() == 25 and lengths.min() <= 12
    assert report["Episode_Metrics/timed_out"] == pytest.approx(timed_out.mean(), rel=1e-6)
    # Terms saw the terminal state: every fallen episode's final angle is past the limit.
    final = report["Episode_Metrics/final_angle/window_values"]
    assert np.all(np.abs(final[~np.isnan(final)][fell]) > FALLEN)


def test_wrap_step_errors():
    metrics = jm.Metrics(terms={"r": jm.Term(lambda t: t.reward)})
    with pytest.raises(TypeError, match="must be a jaxmetrics.Metrics"):
        jm.wrap_step(lambda c, a: (c, c, c, c), {"r": jm.Term(lambda t: t.reward)})
    with pytest.raises(TypeError, match="must be a function"):
        jm.wrap_step(None, metrics)
    three = jm.wrap_step(lambda c, a: (c, c, c), metrics)
    with pytest.raises(TypeError, match=r"\(carry, obs, reward, done\), got tuple of length 3"):
        three((jnp.zeros(2), metrics.init(2)), jnp.zeros(2))
    ok = jm.wrap_step(lambda c, a: (c, c, c, c > 0), metrics)
    with pytest.raises(TypeError, match="carry must be the pair"):
        ok(jnp.zeros(2), jnp.zeros(2))
    bad_done = jm.wrap_step(lambda c, a: (c, c, c, jnp.zeros(3, bool)), metrics)
    with pytest.raises(ValueError, match="done must be a bool array of shape"):
        bad_done((jnp.zeros(2), metrics.init(2)), jnp.zeros(2))


def test_import_jaxmetrics_imports_neither_brax_nor_mujoco():
    code = (
        "import sys, jaxmetrics as jm; jm.wrap_step, jm.Transition; "
        "print(sorted(m for m in ('brax', 'mujoco') if m in sys.modules))"
    )
    root = pathlib.Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=root
    )
    assert out.stdout.strip() == "[]"

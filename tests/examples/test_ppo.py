"""The PPO example: it learns (read back from TensorBoard, against a random policy measured
here), the host loop and the fully-jitted mode write the same values, vmapped seeds each go
to their own run, and its pieces (GAE, observation statistics) match numpy references."""

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax import envs
from tensorboard.backend.event_processing import event_accumulator

import jaxmetrics.brax as jmb
from benchmarks import _hlo
from jaxmetrics.examples import ppo

# The default config at a tenth of its budget: 30 iterations of 64 envs x 32 steps.
CONFIG = ppo.PPOConfig(total_steps=61_440)
SHORT = 3  # iterations of the mode/seed comparisons
SPI = CONFIG.steps_per_iteration


def read_scalars(run_dir: str) -> dict[str, dict[int, float]]:
    """tag -> {step: value}, read back by TensorBoard's own reader."""
    acc = event_accumulator.EventAccumulator(
        run_dir, size_guidance={event_accumulator.SCALARS: 0, event_accumulator.HISTOGRAMS: 0}
    )
    acc.Reload()
    return {t: {e.step: e.value for e in acc.Scalars(t)} for t in acc.Tags()["scalars"]}


def read_histogram_tags(run_dir: str) -> set[str]:
    acc = event_accumulator.EventAccumulator(
        run_dir, size_guidance={event_accumulator.HISTOGRAMS: 0}
    )
    acc.Reload()
    return set(acc.Tags()["histograms"])


def tags_at(scalars: dict[str, dict[int, float]], step: int) -> set[str]:
    return {t for t, by_step in scalars.items() if step in by_step}


@pytest.fixture(scope="module")
def host_run(tmp_path_factory):
    result = ppo.train(CONFIG, str(tmp_path_factory.mktemp("host")), progress=False)
    return result, read_scalars(result.run_dirs[0])


def random_policy_return(num_envs: int = 64, steps: int = 200) -> float:
    """Mean return of the episodes a uniform random policy finishes, counted in numpy."""
    env = envs.training.wrap(
        envs.get_environment(CONFIG.env_name, backend=CONFIG.backend),
        episode_length=CONFIG.episode_length,
    )

    def rollout(key):
        state = env.reset(jax.random.split(key, num_envs))

        def step(state, k):
            action = jax.random.uniform(k, (num_envs, env.action_size), minval=-1.0, maxval=1.0)
            state = env.step(state, action)
            return state, (state.reward, state.done)

        return jax.lax.scan(step, state, jax.random.split(key, steps))[1]

    with jmb.default_promotion():  # the suite runs strict (conftest)
        rewards, dones = jax.jit(rollout)(jax.random.PRNGKey(123))  # Brax: raw uint32 keys
    rewards, dones = np.asarray(rewards, np.float64), np.asarray(dones) > 0
    returns, running = [], np.zeros(num_envs)
    for t in range(steps):
        running += rewards[t]
        returns += running[dones[t]].tolist()
        running[dones[t]] = 0.0
    assert len(returns) > 100, "too few random episodes for a baseline"
    return float(np.mean(returns))


@pytest.mark.slow
def test_ppo_learns_clearly_above_a_random_policy(host_run):
    result, scalars = host_run
    baseline = random_policy_return()
    ret = scalars["Episode_Metrics/episode_return/window_mean"]
    steps = sorted(ret)
    assert steps == [SPI * (i + 1) for i in range(CONFIG.num_iterations)]
    first, last = ret[steps[0]], ret[steps[-1]]
    # The first report is the random-ish initial policy; after 60k steps PPO balances the
    # pole for well over 100 steps where a random policy manages about 5.
    assert first < 3 * baseline
    assert last > 10 * baseline, (baseline, first, last)
    assert result.last[0]["Episode_Metrics/episode_return/window_mean"] == pytest.approx(last)


@pytest.mark.slow
def test_every_metric_is_flushed_each_iteration(host_run):
    result, scalars = host_run
    steps = [SPI * (i + 1) for i in range(CONFIG.num_iterations)]
    for name in ppo.LEARNER_METRICS:
        assert sorted(scalars[f"Train/{name}"]) == steps, name
    for name in ("policy_loss", "value_loss", "grad_norm", "approx_kl"):
        assert f"Train/{name}/std" in scalars
    for term in ("episode_return", "episode_length", "joint_velocity", "control_effort"):
        for stat in ("", "/std", "/count", "/window_mean"):
            assert f"Episode_Metrics/{term}{stat}" in scalars, term + stat
    hists = read_histogram_tags(result.run_dirs[0])
    for term in ("episode_length", "joint_velocity", "control_effort"):
        assert f"Episode_Metrics/{term}/histogram" in hists
    # Period counts partition the lifetime counters: every episode is reported once.
    counts = scalars["Episode_Metrics/episode_return/count"]
    assert sum(counts.values()) == scalars["Counters/episodes"][steps[-1]]
    assert scalars["Counters/env_steps"][steps[-1]] == steps[-1]
    assert scalars["Counters/updates"][steps[-1]] == (
        CONFIG.num_iterations * CONFIG.updates_per_iteration
    )
    # The learning rate is annealed linearly over the run: its first logged value is the
    # mean over the first iteration's updates 0..15 of lr * (1 - k / total).
    total = CONFIG.num_iterations * CONFIG.updates_per_iteration
    k = np.arange(CONFIG.updates_per_iteration, dtype=np.float64)
    expected = np.mean(CONFIG.learning_rate * (1.0 - k / total))
    assert scalars["Train/learning_rate"][steps[0]] == pytest.approx(expected, rel=1e-5)


def assert_same_reports(got, want, steps, what):
    for step in steps:
        assert tags_at(got, step) == tags_at(want, step), (what, step)
        for tag in tags_at(want, step):
            if tag.endswith("/per_sec"):  # host wall-clock rates
                continue
            np.testing.assert_allclose(
                got[tag][step], want[tag][step], rtol=1e-4, atol=1e-5, err_msg=f"{what} {tag}"
            )


@pytest.mark.slow
def test_vmapped_seeds_each_write_their_own_run(host_run, tmp_path):
    _, host = host_run
    result = ppo.train(
        CONFIG, str(tmp_path), seeds=(0, 7), mode="graph", iterations=SHORT, progress=False
    )
    assert result.run_dirs == (str(tmp_path / "seed_0"), str(tmp_path / "seed_7"))
    seed0, seed7 = (read_scalars(d) for d in result.run_dirs)
    steps = [SPI * (i + 1) for i in range(SHORT)]
    assert sorted(seed0["Counters/env_steps"]) == steps
    # The in-graph mode writes what the host loop writes: seed 0 of the vmapped pair is the
    # single-seed host run; seed 7 is another run with the same tags.
    assert_same_reports(seed0, host, steps, "seed 0 vmapped (graph mode) vs host")
    for step in steps:
        assert tags_at(seed7, step) == tags_at(host, step)
    assert result.state.iteration.tolist() == [SHORT, SHORT]
    counts0 = [seed0["Counters/episodes"][s] for s in steps]
    counts7 = [seed7["Counters/episodes"][s] for s in steps]
    assert counts0 != counts7


@pytest.mark.slow
def test_graph_history_mode_writes_what_the_host_loop_writes_with_a_seeds_summary(
    host_run, tmp_path
):
    _, host = host_run
    result = ppo.train(
        CONFIG, str(tmp_path), seeds=(0, 7), mode="graph-history", iterations=SHORT, progress=False
    )
    seed0, seed7 = (read_scalars(d) for d in result.run_dirs)
    steps = [SPI * (i + 1) for i in range(SHORT)]
    assert sorted(seed0["Counters/env_steps"]) == steps
    # Host rates do not exist between the records of a history; the rest is the host run's.
    assert not [t for t in seed0 if t.endswith("/per_sec")]
    host = {t: v for t, v in host.items() if not t.endswith("/per_sec")}
    assert_same_reports(seed0, host, steps, "graph-history seed 0 vs host")
    summary = read_scalars(str(tmp_path / "seeds_summary"))
    tag = "Episode_Metrics/episode_return"
    for step in steps:
        values = np.array([seed0[tag][step], seed7[tag][step]], np.float64)
        np.testing.assert_allclose(summary[tag][step], values.mean(), rtol=1e-6)
        np.testing.assert_allclose(summary[f"{tag}/seeds_std"][step], values.std(ddof=1), rtol=1e-5)
        assert summary[f"{tag}/seeds_count"][step] == 2


def test_gae_matches_a_python_loop():
    rng = np.random.default_rng(0)
    t, n, gamma, lam = 7, 3, 0.9, 0.8
    rewards, values = rng.normal(size=(t, n)), rng.normal(size=(t, n))
    last_value = rng.normal(size=n)
    termination = np.zeros((t, n))
    truncation = np.zeros((t, n))
    termination[2, 0] = termination[5, 1] = 1.0
    truncation[3, 2] = 1.0
    adv, target = jax.jit(ppo.gae, static_argnums=(5, 6))(
        *(jnp.asarray(a, jnp.float32) for a in (rewards, values, last_value)),
        jnp.asarray(termination, jnp.float32),
        jnp.asarray(truncation, jnp.float32),
        gamma,
        lam,
    )
    # Reference: a backward loop; a terminated step does not bootstrap, a truncated step is
    # dropped (advantage 0) and does not pass credit back.
    want = np.zeros((t, n))
    for j in range(n):
        acc = 0.0
        for i in reversed(range(t)):
            if truncation[i, j]:
                acc = 0.0
                continue
            nxt = last_value[j] if i == t - 1 else values[i + 1, j]
            alive = 1.0 - termination[i, j]
            delta = rewards[i, j] + gamma * alive * nxt - values[i, j]
            acc = delta + gamma * lam * alive * acc
            want[i, j] = acc
    np.testing.assert_allclose(adv, want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(target, want + values, rtol=1e-5, atol=1e-6)


def test_observation_statistics_match_numpy():
    rng = np.random.default_rng(1)
    batches = [rng.normal(3.0, 2.0, size=(5, 4, 3)) for _ in range(3)]
    stats = ppo.init_obs_stats(3)
    obs = jnp.zeros((2, 3), jnp.float32)
    # Before any update normalization is the identity (up to the clip).
    np.testing.assert_array_equal(ppo.normalize_obs(stats, obs + 1.5), np.full((2, 3), 1.5))
    update = jax.jit(ppo.update_obs_stats)
    for b in batches:
        stats = update(stats, jnp.asarray(b, jnp.float32))
    flat = np.concatenate([b.reshape(-1, 3) for b in batches])
    assert float(stats.count) == flat.shape[0]
    np.testing.assert_allclose(stats.mean, flat.mean(0), rtol=1e-5)
    np.testing.assert_allclose(stats.m2 / stats.count, flat.var(0), rtol=1e-4)
    x = rng.normal(size=(2, 3))
    want = np.clip((x - flat.mean(0)) / np.sqrt(flat.var(0) + 1e-8), -10, 10)
    np.testing.assert_allclose(
        ppo.normalize_obs(stats, jnp.asarray(x, jnp.float32)), want, rtol=1e-4
    )


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_envs": 0}, r"num_envs=\.\.\.\) must be a positive int"),
        ({"num_minibatches": 3}, "must divide each device's batch"),
        ({"devices": 3}, "devices=3 must divide num_envs"),
        ({"gamma": 1.5}, r"gamma=\.\.\.\) must be in \[0, 1\]"),
        ({"clip_eps": 0.0}, r"clip_eps=\.\.\.\) must be a number > 0"),
        ({"hidden_sizes": [64]}, "hidden_sizes"),
    ],
)
def test_config_errors_name_the_field(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ppo.PPOConfig(**kwargs)


def test_bad_run_arguments_fail_before_any_compile(tmp_path):
    with pytest.raises(ValueError, match="unknown Brax env 'no_such_env'"):
        ppo.make_ppo(ppo.PPOConfig(env_name="no_such_env"))
    with pytest.raises(ValueError, match="use one of"):
        ppo.train(CONFIG, str(tmp_path), mode="jit")
    with pytest.raises(ValueError, match="repeated seeds"):
        ppo.train(CONFIG, str(tmp_path), seeds=(1, 1))
    with pytest.raises(ValueError, match=r"ints in \[0, 2\*\*32\)"):
        ppo.train(CONFIG, str(tmp_path), seeds=(-1,))
    with pytest.raises(ValueError, match="iterations"):
        ppo.train(CONFIG, str(tmp_path), iterations=CONFIG.num_iterations + 1)
    with pytest.raises(ValueError, match=r"mode='graph' or 'graph-history'\) cannot checkpoint"):
        ppo.train(CONFIG, str(tmp_path), mode="graph", resume=True)
    with pytest.raises(ValueError, match=r"mode='graph' or 'graph-history'\) cannot checkpoint"):
        ppo.train(CONFIG, str(tmp_path), mode="graph-history", checkpoint_every=5)
    with pytest.raises(ValueError, match=r"checkpoint_every=\.\.\.\) must be >= 0"):
        ppo.train(CONFIG, str(tmp_path), checkpoint_every=-1)


@pytest.mark.slow
def test_devices_split_the_envs_and_the_rollout_loop_stays_shard_local(tmp_path):
    # Before the first update both runs roll out the same policy on the same envs: the
    # first record's episode metrics agree; the 2-device rollout loop holds no collective
    # (the metrics fold per shard), while its SGD loop all-reduces the gradients.
    # Brax's cheapest backend to compile: the test compares records and reads collectives.
    small = ppo.PPOConfig(
        backend="spring", num_envs=8, unroll_length=16, total_steps=8 * 16 * 2, episode_length=10
    )
    two = ppo.PPOConfig(**{**small.__dict__, "devices": 2})
    first = {}
    for config in (small, two):
        result = ppo.train(config, str(tmp_path / f"d{config.devices}"), progress=False)
        first[config.devices] = read_scalars(result.run_dirs[0])
    shared = {t for t in first[1] if t.startswith("Episode_Metrics/")}
    assert "Episode_Metrics/episode_return/count" in shared
    for tag in shared:
        np.testing.assert_allclose(
            first[2][tag][small.steps_per_iteration],
            first[1][tag][small.steps_per_iteration],
            rtol=1e-5,
            err_msg=tag,
        )
    p = ppo.make_ppo(two)
    state = jax.jit(p.init)(jax.random.key(0))
    hlo = jax.jit(p.iteration).lower(state).compile().as_text()
    loops = _hlo.top_level_loops(hlo)
    rollout, sgd = loops[0], loops[-1]
    assert _hlo.collectives(rollout) == {}, rollout
    assert "all-reduce" in _hlo.collectives(sgd), sgd
    ms = jmb.metrics_state(state.env_state)
    assert ms.shard_counts.hi.shape[0] == 2  # per shard: env steps, episodes


@pytest.mark.parametrize(
    "argv0, prog",
    [
        ("/venv/bin/jaxmetrics-ppo", "jaxmetrics-ppo"),  # the installed script
        # python -m runs the package's __main__.py, and argv[0] is its path
        (
            os.path.join(os.path.dirname(ppo.__file__), "__main__.py"),
            "python -m jaxmetrics.examples.ppo",
        ),
    ],
)
def test_help_names_the_program_it_was_started_as(argv0, prog, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", [argv0, "--help"])
    with pytest.raises(SystemExit) as exit_:
        ppo.main(["--help"])
    assert exit_.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert out.startswith(f"usage: {prog} [-h]")
    assert "to the maximum return (1,000) in under a minute" in out


@pytest.mark.slow
def test_ppo_demo_trains_a_playground_env_by_name(tmp_path, capsys):
    argv = ["--env", "CartpoleBalance", "--steps", "128", "--num-envs", "8", "--unroll-length", "8"]
    argv += ["--episode-length", "4", "--no-progress", "--log-dir", str(tmp_path)]
    assert ppo.main(argv) == 0
    assert (
        "Trained CartpoleBalance (MuJoCo Playground, MJX) for 128 env steps"
        in capsys.readouterr().out
    )
    acc = event_accumulator.EventAccumulator(str(tmp_path / "seed_0"))
    acc.Reload()
    scalars = {t: [e.value for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}
    assert scalars["Counters/env_steps"] == [64.0, 128.0]
    # 8 envs x 8 steps per iteration in episodes of 4: 16 episodes per iteration.
    assert scalars["Episode_Metrics/episode_length"] == [4.0, 4.0]
    assert scalars["Episode_Metrics/episode_length/count"] == [16.0, 16.0]
    for c in ("upright", "centered", "small_control", "small_velocity"):
        (first, second) = scalars[f"Episode_Metrics/reward/{c}"]  # the env's components
        assert 0.0 <= first <= 4.0 and 0.0 <= second <= 4.0
    assert all(np.isfinite(scalars["Train/policy_loss"]))

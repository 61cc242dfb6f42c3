"""Curricula from live statistics (`on_reset`): the example's rule on Brax envs, checked
against a float64 hand loop of the finished episodes, in a jitted rollout and inside
Brax's own `ppo.train` over two devices with its env resets between epochs.

The reference replays what the envs did (each step's done flags, successes, groups and
the level each episode ran at), keeps one window per (group, level) fed in the global env
order, and derives from it what every read must return and the level every new episode
must get.
"""

import functools
import re
from collections import deque

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.training.agents.ppo import train as brax_ppo
from jax.experimental import io_callback

import jaxmetrics as jm
import jaxmetrics.brax as jmb
from jaxmetrics._core import _fresh
from jaxmetrics._host._wrapper_reporter import gathered
from jaxmetrics.examples import curriculum as cur

WINDOW, THRESHOLD, NUM_ENVS = 3, 0.5, 8
G, L = len(cur.GROUPS), cur.LEVELS


def reference_levels(windows: dict) -> np.ndarray:
    """The example's rule, in numpy: per group, the first level not yet mastered."""
    out = []
    for g in range(G):
        level = L - 1
        for k in range(L):
            w = windows[g, k]
            if not (len(w) >= WINDOW and np.mean(np.asarray(w, np.float64)) >= THRESHOLD):
                level = k
                break
        out.append(level)
    return np.asarray(out)


def replay(steps: list[dict]) -> None:
    """Checks each recorded step against the reference: the reads after its episodes
    joined their windows, and the level the next episode of each env that began one
    runs at. A step is `done`, `success`, `level` (the episode's), `group` per env in
    the global order, the reads `rate`/`count` `[G * L]`, and `reset` (Brax's)."""
    windows = {(g, k): deque(maxlen=WINDOW) for g in range(G) for k in range(L)}
    for i, s in enumerate(steps):
        for e in np.flatnonzero(s["done"]):
            windows[int(s["group"][e]), int(s["level"][e])].append(float(s["success"][e]))
        want_count = np.array([len(windows[g, k]) for g in range(G) for k in range(L)])
        want_rate = np.array(
            [np.mean(np.asarray(w, np.float64)) if w else np.nan for w in windows.values()]
        )
        np.testing.assert_array_equal(s["count"], want_count, err_msg=f"step {i}")
        np.testing.assert_allclose(s["rate"], want_rate, rtol=1e-6, err_msg=f"step {i}")
        if i + 1 < len(steps):
            levels = reference_levels(windows)
            began = s["done"] | s["reset"]
            nxt = steps[i + 1]
            # An env that began an episode runs it at its group's level; others keep theirs.
            want = np.where(began, levels[s["group"]], s["level"])
            np.testing.assert_array_equal(
                np.where(nxt["reset"], want, nxt["level"]), want, err_msg=f"step {i + 1}"
            )


def recorded(rule, seen: list, axis: str | None):
    """`rule`, recording what the wrapper hands it (per device under `axis`)."""

    def on_reset(read, state):
        device = 0
        if axis is not None:
            try:
                device = jax.lax.axis_index(axis)
            except NameError:  # Brax's evaluator: not a training step
                return rule(read, state)

        def record(d, rate, count, done, success, level, group, steps):
            seen.append(
                dict(
                    device=int(d),
                    rate=np.asarray(rate),
                    count=np.asarray(count),
                    done=np.asarray(done) != 0,
                    success=np.asarray(success) != 0,
                    level=np.asarray(level),
                    group=np.asarray(group),
                    reset=bool(np.all(np.asarray(steps) == 0)),
                )
            )

        io_callback(
            record,
            None,
            device,
            read("success_rate", "window_mean", by_group=True),
            read("success_rate", "window_count", by_group=True),
            state.done,
            state.info["truncation"],
            state.info["level"],
            state.info["group"],
            state.info["steps"],
            ordered=True,
        )
        return rule(read, state)

    return on_reset


def by_step(seen: list, devices: int) -> list[dict]:
    """Each device's records merged into global steps (device d's envs are the d-th block)."""
    per = [[s for s in seen if s["device"] == d] for d in range(devices)]
    assert len({len(p) for p in per}) == 1, [len(p) for p in per]
    out = []
    for parts in zip(*per):
        for p in parts[1:]:  # every device reads the same global statistics
            np.testing.assert_array_equal(p["rate"], parts[0]["rate"])
            np.testing.assert_array_equal(p["count"], parts[0]["count"])
        assert len({p["reset"] for p in parts}) == 1
        step = {k: np.concatenate([p[k] for p in parts]) for k in ("done", "success")}
        step |= {k: np.concatenate([p[k] for p in parts]) for k in ("level", "group")}
        out.append(step | {k: parts[0][k] for k in ("rate", "count", "reset")})
    return out


def test_levels_follow_the_finished_episodes_of_each_group_in_a_rollout():
    seen: list = []
    metrics = cur.metrics_spec(WINDOW)
    rule = cur.curriculum(WINDOW, THRESHOLD)
    with jmb.default_promotion():
        env = jmb.wrap(
            cur.make_env("spring"),
            metrics,
            episode_length=6,
            on_reset=recorded(rule, seen, None),
        )
        keys = jax.random.split(jax.random.PRNGKey(1), NUM_ENVS)

        @jax.jit
        def rollout(keys):
            state = env.reset(keys)

            def body(s, t):
                a = jax.random.uniform(jax.random.PRNGKey(t), (NUM_ENVS, 1), minval=-1, maxval=1)
                return env.step(s, a), None

            return jax.lax.scan(body, state, jnp.arange(120))[0]

        final = rollout(keys)
    steps = by_step(seen, 1)
    assert len(steps) == 121 and steps[0]["reset"] and not any(s["reset"] for s in steps[1:])
    replay(steps)
    # The curriculum moved: some envs reached level 2 or more, in each group.
    levels, groups = np.asarray(final.info["level"]), np.asarray(final.info["group"])
    assert all(levels[groups == g].max() >= 2 for g in range(G)), (levels, groups)


@pytest.mark.slow
def test_ppo_train_over_two_devices_reads_global_statistics_through_env_resets(
    tmp_path, brax_ppo_on_this_jax
):
    # Brax resets the envs after each epoch (num_resets_per_eval=2): the statistics and
    # so the levels go on; every device reads the statistics of all envs of both.
    seen: list = []
    metrics = cur.metrics_spec(WINDOW)
    logger = jm.Logger(metrics, [jm.TensorBoardWriter(tmp_path)])
    with jmb.default_promotion():
        brax_ppo.train(
            environment=cur.make_env("spring"),
            num_timesteps=2048,
            episode_length=6,
            num_envs=16,
            batch_size=16,
            num_minibatches=2,
            unroll_length=8,
            num_updates_per_batch=1,
            num_evals=2,
            num_eval_envs=4,
            num_resets_per_eval=2,
            max_devices_per_host=2,
            wrap_env_fn=functools.partial(
                jmb.wrap,
                metrics=metrics,
                logger=logger,
                report_every=512,
                on_reset=recorded(cur.curriculum(WINDOW, THRESHOLD), seen, "i"),
            ),
            seed=0,
        )
    logger.close()
    steps = by_step(seen, 2)
    resets = [i for i, s in enumerate(steps) if s["reset"]]
    # The first reset, then one after each of the 2 epochs of 1,024 env steps (64 steps).
    assert resets == [0, 65, 130], resets
    assert len(steps) == 2048 // 16 + 3
    replay(steps)
    assert max(s["level"].max() for s in steps) >= 2


def test_bad_on_reset_is_refused_at_trace_time_naming_the_fix():
    metrics = cur.metrics_spec(WINDOW)
    keys = jax.random.split(jax.random.PRNGKey(0), NUM_ENVS)
    with pytest.raises(TypeError, match=r"on_reset=...\) must be a function \(read, state\)"):
        jmb.wrap(cur.make_env("spring"), metrics, on_reset="level")  # type: ignore[arg-type]

    def dropped_key(read, state):
        return state.replace(info={k: v for k, v in state.info.items() if k != "level"})

    def one_level_for_all(read, state):
        return state.replace(info={**state.info, "level": jnp.int32(1)})

    for rule, match in (
        (dropped_key, r"must return the env state it was given with the same structure"),
        (one_level_for_all, r"returned state.*\['level'\] of shape \(\) where the env state"),
    ):
        with jmb.default_promotion():
            env = jmb.wrap(cur.make_env("spring"), metrics, on_reset=rule)
            with pytest.raises(ValueError, match=match):
                jax.eval_shape(env.reset, keys)


def _gathered_bytes(hlo: str) -> int:
    """Bytes the all-gathers of a compiled program produce."""
    total = 0
    for line in hlo.splitlines():
        if " all-gather(" in line or " all-gather-start(" in line:
            shapes = re.findall(r"([fsu])(32|64)\[([\d,]*)\]", line.split("all-gather")[0])
            for _, bits, dims in shapes:
                total += int(np.prod([int(d) for d in dims.split(",") if d])) * int(bits) // 8
    return total


def test_a_read_across_devices_gathers_what_its_statistic_needs():
    # Under a trainer's pmap the wrapper gathers the devices' statistics for a global read
    # on every step: only those the statistic merges from cross, not the EMA histories
    # (most of the state) for a window read.
    # The defaults: a window of 100 and an EMA of 0.01, exact across devices with its
    # newest 2,207 values.
    level = jm.groups(lambda s: s["level"], ("easy", "mid", "hard"))
    metrics = jm.Metrics(terms={"success_rate": jm.success_rate(lambda s: s["ok"], groups=level)})
    state = _fresh.fresh(metrics._rows, NUM_ENVS, 1, ema_history=True)
    whole = sum(x.nbytes for x in jax.tree.leaves(state.finished))
    two = jax.tree.map(lambda x: jnp.stack([x, x]), state)

    def cost(stat):
        def read(s):
            return metrics.read(gathered(s, "i"), "success_rate", stat, by_group=True)

        return _gathered_bytes(jax.pmap(read, axis_name="i").lower(two).compile().as_text())

    assert cost("ema") > whole  # the exact merge of an EMA needs its history
    assert 0 < cost("window_mean") < whole / 10
    assert 0 < cost("mean") < cost("window_mean")

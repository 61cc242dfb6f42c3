"""Wrappers that report by themselves (`wrap_step(..., logger=)`): one record per period,
in order, equal to a float64 Python loop over the same rewards and dones; one run over all
devices under `pmap`; one run per seed under `vmap`; bad input named at build or trace time.

Brax's own trainer with the reporting wrapper is in `test_brax_reporting.py`."""

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmetrics as jm

NUM_ENVS, STEPS, PERIOD_CALLS, WINDOW = 8, 24, 6, 5


def _spec() -> jm.Metrics:
    return jm.Metrics(
        terms={
            "ret": jm.Term(
                lambda t: t.reward,
                reduce="sum",
                stats=("mean", "std", "max", "count", jm.window(WINDOW), jm.ema(0.5)),
            )
        }
    )


def _episodes(seed: int, num_envs: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Rewards and dones `[steps, num_envs]` (float32 rewards, ~1 in 3 steps ends)."""
    rng = np.random.default_rng(seed)
    rewards = rng.normal(1.0, 2.0, (steps, num_envs)).astype(np.float32)
    dones = rng.random((steps, num_envs)) < 0.35
    return rewards, dones


def _step(carry, inputs):
    """A step that replays recorded rewards and dones (the carry is unused)."""
    reward, done = inputs
    return carry, reward, reward, done


def _reference(rewards: np.ndarray, dones: np.ndarray, period_calls: int) -> list[dict]:
    """Per period (in order): count, mean, std, max, window mean and EMA of the returns of
    the episodes that ended in it, in float64, envs in index order within a step."""
    acc = np.zeros(rewards.shape[1])
    window: list[float] = []
    ema = None
    out, ended = [], []
    for t in range(rewards.shape[0]):
        acc += rewards[t].astype(np.float64)
        for e in np.flatnonzero(dones[t]):
            ended.append(acc[e])
            window = (window + [acc[e]])[-WINDOW:]
            ema = acc[e] if ema is None else 0.5 * acc[e] + 0.5 * ema
            acc[e] = 0.0
        if (t + 1) % period_calls == 0:
            x = np.asarray(ended)
            out.append(
                {
                    "count": len(x),
                    "mean": x.mean() if len(x) else None,
                    "std": x.std() if len(x) else None,
                    "max": x.max() if len(x) else None,
                    "window_mean": np.mean(window) if window else None,
                    "ema": ema,
                }
            )
            ended = []
    return out


def _check(records, expected, num_envs):
    assert [r.step for r in records] == [
        (i + 1) * PERIOD_CALLS * num_envs for i in range(len(expected))
    ]
    for r, want in zip(records, expected):
        s = r.scalars
        assert s["Episode_Metrics/ret/count"] == want["count"]
        assert s["Counters/env_steps"] == r.step
        for stat, tag in (
            ("mean", "Episode_Metrics/ret"),
            ("std", "Episode_Metrics/ret/std"),
            ("max", "Episode_Metrics/ret/max"),
            ("window_mean", "Episode_Metrics/ret/window_mean"),
            ("ema", "Episode_Metrics/ret/ema"),
        ):
            if want[stat] is None:
                assert tag not in s
            else:
                assert s[tag] == pytest.approx(want[stat], rel=1e-5, abs=1e-5), (r.step, stat)


def _run_scan(wrapped, rewards, dones, num_envs):
    def run(r, d):
        carry = wrapped.init(jnp.zeros(()), num_envs)
        body = lambda c, x: (wrapped(c, x)[0], None)  # noqa: E731
        return jax.lax.scan(body, carry, (r, d))[0]

    return run


def test_a_reporting_step_writes_each_period_equal_to_a_float64_loop():
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(0, NUM_ENVS, STEPS)
    with jm.Logger(metrics, [memory]) as logger:
        wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=PERIOD_CALLS * NUM_ENVS)
        run = jax.jit(_run_scan(wrapped, rewards, dones, NUM_ENVS))
        carry = run(rewards, dones)
        # The state the loop hands back holds no more than the steps since the last report.
        assert int(carry[2]) == 0
    expected = _reference(rewards, dones, PERIOD_CALLS)
    assert len(memory.records) == STEPS // PERIOD_CALLS
    _check(memory.records, expected, NUM_ENVS)


def test_the_period_is_rounded_up_to_whole_steps_of_the_batch():
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(1, NUM_ENVS, STEPS)
    with jm.Logger(metrics, [memory]) as logger:
        # 41 env steps = 5.1 steps of 8 envs: a report every 6 steps (48 env steps).
        wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=41)
        jax.jit(_run_scan(wrapped, rewards, dones, NUM_ENVS))(rewards, dones)
    _check(memory.records, _reference(rewards, dones, PERIOD_CALLS), NUM_ENVS)


def test_the_default_period_is_100_steps_of_the_batch():
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(2, 2, 250)
    with jm.Logger(metrics, [memory]) as logger:
        wrapped = jm.wrap_step(_step, metrics, logger=logger)
        jax.jit(_run_scan(wrapped, rewards, dones, 2))(rewards, dones)
    assert [r.step for r in memory.records] == [200, 400]


def test_vmapped_seeds_report_each_to_its_own_run():
    seeds = 3
    metrics = _spec()
    memory = [jm.MemoryWriter() for _ in range(seeds)]
    data = [_episodes(10 + s, NUM_ENVS, STEPS) for s in range(seeds)]
    rewards = np.stack([r for r, _ in data])
    dones = np.stack([d for _, d in data])
    with jm.Logger(metrics, lambda run: [memory[run]], runs=seeds) as logger:
        wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=PERIOD_CALLS * NUM_ENVS)
        jax.jit(jax.vmap(_run_scan(wrapped, rewards, dones, NUM_ENVS)))(rewards, dones)
        # One host callback per period end carries every seed.
        assert logger.emit_calls == STEPS // PERIOD_CALLS
    for s in range(seeds):
        _check(memory[s].records, _reference(*data[s], PERIOD_CALLS), NUM_ENVS)


def test_pmapped_envs_report_one_run_over_all_devices():
    devices = 2
    per_device = NUM_ENVS // devices
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(3, NUM_ENVS, STEPS)
    # Device d steps the d-th block of envs, as Brax's trainers split them.
    split = lambda x: np.stack(np.split(x, devices, axis=1))  # noqa: E731
    with jm.Logger(metrics, [memory]) as logger:
        wrapped = jm.wrap_step(
            _step,
            metrics,
            logger=logger,
            report_every=PERIOD_CALLS * NUM_ENVS,
            axis_name="i",
        )
        run = jax.pmap(
            _run_scan(wrapped, None, None, per_device),
            axis_name="i",
            devices=jax.devices("cpu")[:devices],
        )
        jax.block_until_ready(run(split(rewards), split(dones)))
        assert logger.emit_calls == STEPS // PERIOD_CALLS  # one writer, not one per device
    # Windows and EMA in the order of the global env index, as on one device.
    _check(memory.records, _reference(rewards, dones, PERIOD_CALLS), NUM_ENVS)


def test_a_pmapped_step_folds_with_no_collective_outside_the_report():
    metrics = _spec()
    logger = jm.Logger(metrics, [jm.MemoryWriter()])
    wrapped = jm.wrap_step(_step, metrics, logger=logger, axis_name="i")
    rewards, dones = _episodes(4, 4, 3)
    run = jax.pmap(_run_scan(wrapped, None, None, 2), axis_name="i", devices=jax.devices("cpu")[:2])
    split = lambda x: np.stack(np.split(x, 2, axis=1))  # noqa: E731
    jaxpr = jax.make_jaxpr(run)(split(rewards), split(dones)).jaxpr
    with pytest.warns(RuntimeWarning, match="wrote no record"):  # traced, never run
        logger.close()
    found = list(_collectives(jaxpr, ()))
    assert found, "the report gathers the devices' statistics"
    # Each collective sits under a cond (the period end) inside the step loop.
    for name, path in found:
        assert "scan" in path and "cond" in path[path.index("scan") :], (name, path)


def _collectives(jaxpr, path):
    """(primitive, enclosing primitives) of every collective in a jaxpr, recursively."""
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name in ("all_gather", "psum", "all_to_all", "ppermute", "pmax", "pmin"):
            yield name, path
        for sub in _sub_jaxprs(eqn.params):
            yield from _collectives(sub, (*path, name))


def _sub_jaxprs(params):
    """The jaxprs in an equation's params (`jax.extend.core.jaxprs_in_params` from JAX
    0.10 on; written out for the declared floor)."""
    for value in params.values():
        for v in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(v, jax.extend.core.ClosedJaxpr):
                yield v.jaxpr
            elif isinstance(v, jax.extend.core.Jaxpr):
                yield v


def test_closing_after_training_writes_everything_once_also_when_retraced():
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(5, NUM_ENVS, STEPS)
    logger = jm.Logger(metrics, [memory])
    wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=PERIOD_CALLS * NUM_ENVS)

    def run(carry, r, d):
        return jax.lax.scan(lambda c, x: (wrapped(c, x)[0], None), carry, (r, d))[0]

    carry = jax.jit(run)(wrapped.init(jnp.zeros(()), NUM_ENVS), rewards[:9], dones[:9])
    # The trainer traces its step again (a new jit of the same wrapped env) and goes on
    # from the state it kept: each period is written once, the one cut by the retrace too.
    jax.jit(lambda c, r, d: run(c, r, d))(carry, rewards[9:], dones[9:])
    logger.close()
    logger.close()
    assert len(memory.records) == STEPS // PERIOD_CALLS
    _check(memory.records, _reference(rewards, dones, PERIOD_CALLS), NUM_ENVS)


def test_bad_input_is_named_when_the_wrapper_is_built():
    metrics = _spec()
    logger = jm.Logger(metrics, [jm.MemoryWriter()])
    other = jm.Metrics(terms={"x": jm.Term(lambda t: t.reward)})
    with pytest.raises(ValueError, match="Logger was built for another Metrics spec"):
        jm.wrap_step(_step, other, logger=logger)
    for bad in (0, 2**63):  # 2^33 used to pass here and fail at trace time on an "y"
        with pytest.raises(
            ValueError, match=r"report_every=\.\.\.\) must be an int in \[1, 2\^62\]"
        ):
            jm.wrap_step(_step, metrics, logger=logger, report_every=bad)
    with pytest.raises(TypeError, match=r"logger=\.\.\.\) must be a jaxmetrics.Logger"):
        jm.wrap_step(_step, metrics, logger=[jm.MemoryWriter()])
    with pytest.raises(TypeError, match=r"axis_name=\.\.\.\) must be a str"):
        jm.wrap_step(_step, metrics, logger=logger, axis_name=0)
    logged_only = jm.Metrics(logged=["loss"])
    with jm.Logger(logged_only, []) as other_logger:
        with pytest.raises(ValueError, match="counts no env steps"):
            jm.wrap_step(_step, logged_only, logger=other_logger)
    wrapped = jm.wrap_step(_step, metrics, logger=logger)
    with pytest.raises(TypeError, match=r"triple \(carry, metrics_state, clock\)"):
        wrapped((jnp.zeros(()), metrics.init(2)), (jnp.zeros(2), jnp.zeros(2, bool)))
    logger.close()


def test_seeds_vmapped_against_a_logger_of_other_runs_are_refused_at_trace_time():
    metrics = _spec()
    rewards, dones = _episodes(6, 2, 4)
    with jm.Logger(metrics, lambda run: [jm.MemoryWriter()], runs=2) as logger:
        wrapped = jm.wrap_step(_step, metrics, logger=logger)
        run = jax.vmap(_run_scan(wrapped, None, None, 2))
        stacked = (np.stack([rewards] * 3), np.stack([dones] * 3))
        with pytest.raises(ValueError, match="vmapped over 3 seeds.*runs=3"):
            jax.jit(run)(*stacked)
        nested = jax.vmap(jax.vmap(_run_scan(wrapped, None, None, 2)))
        with pytest.raises(ValueError, match="nested vmaps"):
            jax.jit(nested)(np.stack([stacked[0][:2]] * 2), np.stack([stacked[1][:2]] * 2))
        # Traced, refused, never run: no record, and close says so.
        with pytest.warns(RuntimeWarning, match="traced but wrote no record"):
            logger.close()


def test_a_trainer_reset_of_the_envs_continues_the_steps_and_says_so():
    # Brax's num_resets_per_eval (Playground's configs set 1 or 10) resets the envs, and
    # with them the wrapper's statistics and env-step count, between training epochs.
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(7, NUM_ENVS, STEPS)
    logger = jm.Logger(metrics, [memory])
    wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=PERIOD_CALLS * NUM_ENVS)
    run = jax.jit(_run_scan(wrapped, None, None, NUM_ENVS))
    half = STEPS // 2
    run(rewards[:half], dones[:half])
    run(rewards[half:], dones[half:])  # starts from wrapped.init again: a reset
    with pytest.warns(
        RuntimeWarning,
        match=r"run 0: the reporting wrapper's env steps started again after its record at "
        r"step 96",
    ):
        logger.close()
    records = memory.records
    # Steps and the env-step counter go on; statistics are those of each stretch.
    _check(records[:2], _reference(rewards[:half], dones[:half], PERIOD_CALLS), NUM_ENVS)
    second = _reference(rewards[half:], dones[half:], PERIOD_CALLS)
    assert [r.step for r in records[2:]] == [144, 192]
    assert [r.scalars["Counters/env_steps"] for r in records] == [48, 96, 144, 192]
    assert all(r.scalars["Counters/env_steps/per_sec"] > 0 for r in records[1:])
    for r, want in zip(records[2:], second):
        assert r.scalars["Episode_Metrics/ret/count"] == want["count"]
        assert r.scalars["Episode_Metrics/ret"] == pytest.approx(want["mean"], rel=1e-5)
    # A third stretch after close(), again from a fresh state: its lost records are named
    # by the steps they would have had (they were named by the wrapper's own count, 48).
    jax.block_until_ready(run(rewards[:half], dones[:half]))
    with pytest.raises(jm.ReportsLostError, match=r"2 record\(s\) .* at step 240 on"):
        logger.close()
    assert len(memory.records) == 4


def test_a_second_wrapper_on_one_logger_is_refused_at_trace_time():
    # Each Brax ppo.train builds its env, and so its wrapper, anew: a second training's
    # records would have gone on from the first's last step (1,280 where Brax says 0).
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(9, NUM_ENVS, PERIOD_CALLS)
    with jm.Logger(metrics, [memory]) as logger:
        first = jm.wrap_step(_step, metrics, logger=logger, report_every=PERIOD_CALLS * NUM_ENVS)
        jax.jit(_run_scan(first, rewards, dones, NUM_ENVS))(rewards, dones)
        second = jm.wrap_step(_step, metrics, logger=logger, report_every=PERIOD_CALLS * NUM_ENVS)
        with pytest.raises(
            ValueError,
            match=r"already takes the reports of another reporting wrapper.*Create a new "
            r"Logger for each training",
        ):
            jax.jit(_run_scan(second, rewards, dones, NUM_ENVS))(rewards, dones)
    assert [r.step for r in memory.records] == [PERIOD_CALLS * NUM_ENVS]


def test_envs_reset_under_an_unnamed_pmap_still_merge_exactly():
    # Brax's SAC resets its envs under `jax.pmap(env.reset)` (no axis name) and steps them
    # under the axis "i": the states must still merge exactly at a report.
    devices, per_device = 2, NUM_ENVS // 2
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(8, NUM_ENVS, STEPS)
    split = lambda x: np.stack(np.split(x, devices, axis=1))  # noqa: E731
    cpus = jax.devices("cpu")[:devices]
    with jm.Logger(metrics, [memory]) as logger:
        wrapped = jm.wrap_step(
            _step, metrics, logger=logger, report_every=PERIOD_CALLS * NUM_ENVS, axis_name="i"
        )
        carry = jax.pmap(lambda z: wrapped.init(z, per_device), devices=cpus)(jnp.zeros(devices))

        def run(carry, r, d):
            return jax.lax.scan(lambda c, x: (wrapped(c, x)[0], None), carry, (r, d))[0]

        jax.block_until_ready(
            jax.pmap(run, axis_name="i", devices=cpus)(carry, split(rewards), split(dones))
        )
    _check(memory.records, _reference(rewards, dones, PERIOD_CALLS), NUM_ENVS)


def test_misuse_found_at_trace_time_is_named_with_its_fix():
    metrics = _spec()
    rewards, dones = _episodes(0, NUM_ENVS, 4)
    # A period past the int32 clock: refused at trace time, naming the largest period.
    with jm.Logger(metrics, [jm.MemoryWriter()]) as logger:
        wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=2**40)
        with pytest.raises(
            ValueError, match=r"report_every=1099511627776 is .* at most 17179869176"
        ):
            jax.jit(_run_scan(wrapped, rewards, dones, NUM_ENVS))(rewards, dones)
    # A Logger of 2 runs and a wrapper that is not vmapped: not all records to run 0.
    memory = [jm.MemoryWriter(), jm.MemoryWriter()]
    logger = jm.Logger(metrics, lambda run: [memory[run]], runs=2)
    wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=NUM_ENVS)
    jax.jit(_run_scan(wrapped, rewards, dones, NUM_ENVS))(rewards, dones)
    with pytest.raises(jm.WriterError, match=r"runs=2, but the wrapper is not vmapped"):
        logger.close()
    assert memory[0].records == memory[1].records == []
    # A closed Logger: named as the wrapper's, when built and when traced after a close.
    logger = jm.Logger(metrics, [jm.MemoryWriter()])
    wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=NUM_ENVS)
    logger.close()
    with pytest.raises(RuntimeError, match=r"wrap_step\(logger=\.\.\.\): the Logger is closed"):
        jm.wrap_step(_step, metrics, logger=logger)
    with pytest.raises(RuntimeError, match=r"Logger given to a reporting wrapper .* is closed"):
        jax.jit(_run_scan(wrapped, rewards, dones, NUM_ENVS))(rewards, dones)


def test_an_unvmapped_wrapper_of_a_closed_logger_of_2_runs_is_counted_lost_not_dropped():
    # The "not vmapped over seeds" error was stored when the record came, also after close(),
    # where nothing raised it any more: the records were lost unsaid.
    metrics, memory = _spec(), [jm.MemoryWriter(), jm.MemoryWriter()]
    rewards, dones = _episodes(0, NUM_ENVS, 4)
    logger = jm.Logger(metrics, lambda run: [memory[run]], runs=2)
    wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=NUM_ENVS)
    training = jax.jit(_run_scan(wrapped, rewards, dones, NUM_ENVS)).lower(rewards, dones)
    training = training.compile()  # traced while the Logger is open
    with pytest.warns(RuntimeWarning, match="traced but wrote no record"):
        logger.close()
    jax.block_until_ready(training(rewards, dones))
    with pytest.raises(jm.ReportsLostError, match=r"4 record\(s\) reached this Logger after"):
        logger.close()
    assert memory[0].records == memory[1].records == []


def test_a_wrapper_that_never_reported_says_so_at_close_naming_its_period():
    # ppo.train with report_every past num_timesteps wrote 0 records and close() said
    # nothing.
    metrics = _spec()
    rewards, dones = _episodes(0, NUM_ENVS, 4)
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])
    wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=100 * NUM_ENVS)
    jax.jit(_run_scan(wrapped, rewards, dones, NUM_ENVS))(rewards, dones)
    with pytest.warns(RuntimeWarning, match=r"wrote no record: it reports every 800 env steps"):
        logger.close()
    assert memory.records == []


def test_nested_vmaps_over_all_of_a_logger_s_seeds_are_told_to_flatten():
    # vmap(2) of vmap(3) against runs=6 was told "create the Logger with runs=3".
    metrics = _spec()
    rewards, dones = _episodes(6, 2, 4)
    with jm.Logger(metrics, lambda run: [jm.MemoryWriter()], runs=6) as logger:
        wrapped = jm.wrap_step(_step, metrics, logger=logger)
        nested = jax.vmap(jax.vmap(_run_scan(wrapped, None, None, 2)))
        stacked = (np.stack([np.stack([rewards] * 3)] * 2), np.stack([np.stack([dones] * 3)] * 2))
        with pytest.raises(
            ValueError,
            match=r"runs=6: .*inner of nested vmaps over 6 seeds.*one flattened axis of 6",
        ):
            jax.jit(nested)(*stacked)
        with pytest.warns(RuntimeWarning, match="traced but wrote no record"):
            logger.close()


@pytest.mark.parametrize("channel", ["io_callback", "ring"])
def test_a_logger_closed_mid_training_counts_the_later_records_and_the_training_goes_on(
    channel, caplog
):
    # Closed between two calls of the compiled training (as between Brax's epochs), the
    # io_callback's receiver raised into XLA: `JaxRuntimeError: INTERNAL: CpuCallback
    # error` ended the training; through the ring the later records were lost unsaid.
    metrics, memory = _spec(), jm.MemoryWriter()
    rewards, dones = _episodes(3, NUM_ENVS, 2 * 2 * PERIOD_CALLS)
    logger = jm.Logger(metrics, [memory], report_channel=channel)
    wrapped = jm.wrap_step(_step, metrics, logger=logger, report_every=PERIOD_CALLS * NUM_ENVS)

    @jax.jit
    def epoch(carry, r, d):
        return jax.lax.scan(lambda c, x: (wrapped(c, x)[0], None), carry, (r, d))[0]

    half = 2 * PERIOD_CALLS
    carry = epoch(wrapped.init(jnp.zeros(()), NUM_ENVS), rewards[:half], dones[:half])
    logger.close()
    carry = jax.block_until_ready(epoch(carry, rewards[half:], dones[half:]))
    report = metrics.to_host(metrics.compute(carry[1]))
    assert report["Counters/env_steps"] == 4 * PERIOD_CALLS * NUM_ENVS  # it ran to its end
    assert [r.step for r in memory.records] == [48, 96]
    with pytest.raises(
        jm.ReportsLostError,
        match=r"2 record\(s\) reached this Logger after its close\(\) and were not "
        r"written, from run 0's record at step 144 on: .* Close the Logger after the "
        r"training returns",
    ) as lost:
        logger.close()
    assert lost.value.lost == 2
    (logged,) = [r for r in caplog.records if r.name == "jaxmetrics"]
    assert "closed while the training still runs: its record of run 0 at step 144" in (
        logged.getMessage()
    )
    logger.close()  # said once
    assert [r.step for r in memory.records] == [48, 96]

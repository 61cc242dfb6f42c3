"""The host flush: non-blocking, drained in order by close(), durable across SIGKILL,
deterministic non-finite errors, counters per second, timers, vmapped runs."""

import gc
import inspect
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import weakref

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tensorboard.backend.event_processing import event_accumulator as ea

import jaxmetrics as jm
from jaxmetrics._core import _stream

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


class GatedSink:
    """A writer whose write blocks until the test opens the gate (a slow disk)."""

    def __init__(self, gate: threading.Event):
        self.gate = gate
        self.steps: list[int] = []
        self.closed = False

    def open(self, tags):
        pass

    def write(self, record):
        if not self.gate.wait(timeout=60):
            raise TimeoutError("the test never opened the gate")
        self.steps.append(record.step)

    def close(self):
        self.closed = True


def _log_metrics(**kw):
    return jm.Metrics(logged={"x": jm.Logged(**kw)})


def test_flush_returns_before_the_writer_finishes_and_close_waits_for_it():
    metrics = _log_metrics()
    gate = threading.Event()
    sink = GatedSink(gate)
    logger = jm.Logger(metrics, [sink])
    state = metrics.init(1)
    for step in range(3):
        state = logger.flush(metrics.log(state, {"x": jnp.float32(step)}), step)
    assert sink.steps == []  # every flush returned while the sink was still blocked
    closer = threading.Thread(target=logger.close)
    closer.start()
    closer.join(timeout=0.5)
    assert closer.is_alive() and not sink.closed  # close() is waiting for the sink
    gate.set()
    closer.join(timeout=60)
    assert not closer.is_alive()
    assert sink.steps == [0, 1, 2] and sink.closed


def test_flush_blocks_only_when_max_pending_flushes_are_queued():
    metrics = _log_metrics()
    gate = threading.Event()
    sink = GatedSink(gate)
    logger = jm.Logger(metrics, [sink], max_pending=1)
    state = logger.flush(metrics.init(1), 0)
    second = threading.Thread(target=logger.flush, args=(state, 1))
    second.start()
    second.join(timeout=0.5)
    assert second.is_alive()  # back-pressure: the one pending slot is taken
    gate.set()
    second.join(timeout=60)
    logger.close()
    assert sink.steps == [0, 1]


def test_returned_state_is_reset_and_keeps_windows_and_counters():
    metrics = jm.Metrics(logged={"x": jm.Logged(stats=("mean", "count", jm.window(3)))})
    memory = jm.MemoryWriter()
    with jm.Logger(metrics, [memory]) as logger:
        state = metrics.log(metrics.init(1), {"x": jnp.array([1.0, 2.0], jnp.float32)})
        state = logger.flush(state, 0)
        state = logger.flush(metrics.log(state, {"x": jnp.float32(4.0)}), 1)
    s0, s1 = (r.scalars for r in memory.records)
    assert (s0["Train/x"], s0["Train/x/count"]) == (1.5, 2)
    assert (s1["Train/x"], s1["Train/x/count"]) == (4.0, 1)  # period reset
    assert s1["Train/x/window_mean"] == pytest.approx(7.0 / 3.0)  # window carried on


_CHILD = """
import sys, time
import jax.numpy as jnp
import jaxmetrics as jm
from jaxmetrics._core import _stream

root, n = sys.argv[1], int(sys.argv[2])
metrics = jm.Metrics(logged=["x"])
logger = jm.Logger(metrics, [jm.TensorBoardWriter(root + "/tb"), jm.JsonlWriter(root + "/m.jsonl")])
state = metrics.init(1)
step = 0
while True:
    state = logger.flush(metrics.log(state, {"x": jnp.float32(step * 0.5)}), step)
    step += 1
    if step == n:
        logger.wait()
        print("READY", flush=True)
    if step > n:
        time.sleep(0.005)
"""


def test_everything_flushed_before_sigkill_is_readable(tmp_path):
    n = 20
    path = os.pathsep.join(p for p in (ROOT, os.environ.get("PYTHONPATH")) if p)
    env = dict(os.environ, PYTHONPATH=path, JAX_PLATFORMS="cpu")
    child = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(tmp_path), str(n)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    try:
        line = child.stdout.readline()
        assert line.strip() == "READY", child.stderr.read()
        time.sleep(0.3)  # let it keep flushing, so the kill lands mid-stream
    finally:
        child.send_signal(signal.SIGKILL)
        child.communicate(timeout=60)
    assert child.returncode == -signal.SIGKILL

    acc = ea.EventAccumulator(str(tmp_path / "tb"), size_guidance={ea.SCALARS: 0})
    acc.Reload()
    tb = [(e.step, e.value) for e in acc.Scalars("Train/x")]
    with open(tmp_path / "m.jsonl", "rb") as f:
        raw = f.read().split(b"\n")
    # One unbuffered write per line: at most the last line can be cut by the kill.
    lines = [json.loads(x) for x in raw[:-1]]
    js = [(d["step"], d["scalars"]["Train/x"]) for d in lines]
    for got in (tb, js):
        steps = [s for s, _ in got]
        assert steps == list(range(len(steps))) and len(steps) >= n  # every flushed step, in order
        np.testing.assert_array_equal([v for _, v in got], np.arange(len(steps)) * 0.5)


def test_a_flush_that_raises_has_done_nothing_so_flushing_again_counts_once(tmp_path):
    # The raising flush used to queue its own report first: a caller that caught the
    # error and flushed its state again wrote that period twice.
    metrics = _log_metrics(nonfinite="raise")
    path = tmp_path / "m.jsonl"
    logger = jm.Logger(metrics, [jm.JsonlWriter(path)])
    state = logger.flush(metrics.log(metrics.init(1), {"x": jnp.float32(np.nan)}), 0)
    state = metrics.log(state, {"x": jnp.float32(2.0)})
    with pytest.raises(jm.NonFiniteError, match="step 0, run 0: logged value 'x': 1 non-finite"):
        logger.flush(state, 1)
    state = logger.flush(state, 1)
    logger.close()
    with open(path) as f:
        got = [
            (d["step"], d["scalars"].get("Train/x"), d["scalars"]["Train/x/count"])
            for d in map(json.loads, f)
        ]
    assert got == [(0, None, 0), (1, 2.0, 1)]


def test_nonfinite_raise_in_the_last_flush_surfaces_at_close(tmp_path):
    metrics = _log_metrics(nonfinite="raise")
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [memory])
    state = logger.flush(metrics.log(metrics.init(1), {"x": jnp.float32(1.0)}), 0)
    logger.flush(metrics.log(state, {"x": jnp.float32(np.inf)}), 1)
    with pytest.raises(jm.NonFiniteError, match="step 1, run 0: "):
        logger.close()
    assert [r.step for r in memory.records] == [0, 1]


def test_nonfinite_skip_warns_at_the_callers_line_naming_metric_run_and_step():
    metrics = _log_metrics()
    logger = jm.Logger(metrics, lambda run: [jm.MemoryWriter()], runs=2)
    log = jax.vmap(lambda s, v: metrics.log(s, {"x": v}))
    state = jax.vmap(lambda _: metrics.init(1))(jnp.arange(2))
    state = logger.flush(log(state, jnp.array([1.0, np.nan], jnp.float32)), 4)
    want = (
        r"^step 4, run 1: logged value 'x': 1 non-finite value\(s\) left out or statistic\(s\) "
        r"overflowed \(Train/x/nonfinite\)$"
    )
    with pytest.warns(RuntimeWarning, match=want) as caught:
        line = inspect.currentframe().f_lineno + 1
        state = logger.flush(state, 5)
    assert len(caught) == 1  # run 0 was clean
    assert (caught[0].filename, caught[0].lineno) == (__file__, line)
    state = logger.flush(log(state, jnp.array([np.inf, 2.0], jnp.float32)), 6)
    with pytest.warns(RuntimeWarning, match="step 6, run 0: ") as caught:
        line = inspect.currentframe().f_lineno + 1
        logger.close()
    assert (caught[0].filename, caught[0].lineno) == (__file__, line)


def test_writer_errors_surface_on_the_callers_thread():
    class Broken:
        def open(self, tags):
            pass

        def write(self, record):
            raise OSError("disk full")

        def close(self):
            pass

    metrics = _log_metrics()
    memory = jm.MemoryWriter()
    logger = jm.Logger(metrics, [Broken(), memory])
    logger.flush(metrics.init(1), 7)
    with pytest.raises(RuntimeError, match="failed at step 7: OSError\\('disk full'\\)"):
        logger.wait()
    logger.close()
    assert [r.step for r in memory.records] == [7]  # the other writers still got it


def test_counters_per_second_are_growth_over_host_time_between_flushes():
    metrics = jm.Metrics(terms={"r": lambda x: x}, counters=["updates"])
    memory = jm.MemoryWriter()
    state = metrics.init(4)
    with jm.Logger(metrics, [memory]) as logger:
        for it in range(3):
            state = metrics.update(state, jnp.ones(4), jnp.arange(4) < it)
            state = metrics.increment(state, "updates", 5)
            state = logger.flush(state, it)
    r = memory.records
    assert "Counters/env_steps/per_sec" not in r[0].scalars  # needs two records
    for prev, cur in zip(r, r[1:]):
        dt = cur.wall_time - prev.wall_time
        for c, inc in (("env_steps", 4), ("updates", 5)):
            assert cur.scalars[f"Counters/{c}"] - prev.scalars[f"Counters/{c}"] == inc
            assert cur.scalars[f"Counters/{c}/per_sec"] == pytest.approx(inc / dt)
    assert [x.scalars["Counters/episodes"] for x in r] == [0, 1, 3]


def test_records_are_stamped_when_the_device_has_computed_the_report():
    # A host loop runs ahead of the device (flush returns once it has dispatched): rates
    # over dispatch times would be far too high (the PPO demo's first steps/s read 20x
    # its steady value). Records carry the time their report reached the host instead.
    metrics = jm.Metrics(logged=["x"], counters=["updates"])
    a = jax.random.normal(jax.random.key(0), (512, 512), jnp.float32) / 32.0

    @jax.jit
    def iteration(state):
        y = jax.lax.fori_loop(0, 40, lambda i, y: jnp.tanh(y @ a), a)
        return metrics.increment(metrics.log(state, {"x": jnp.sum(y)}), "updates")

    state = jax.block_until_ready(iteration(metrics.init(1)))  # compiled
    timings = []
    for _ in range(3):
        start = time.perf_counter()
        jax.block_until_ready(iteration(state))
        timings.append(time.perf_counter() - start)
    seconds = min(timings)  # one iteration on the device, least disturbed by other load
    memory = jm.MemoryWriter()
    with jm.Logger(metrics, [memory]) as logger:
        logger.flush(state, 0)  # compiles the flush
        logger.wait()
        start = time.time()
        for step in (1, 2, 3):
            state = logger.flush(iteration(state), step)
    records = memory.records[1:]
    for k, r in enumerate(records, start=1):
        assert r.wall_time - start >= 0.5 * k * seconds, (k, r.wall_time - start, seconds)
    for r in records[1:]:
        assert r.scalars["Counters/updates/per_sec"] <= 2.0 / seconds


def test_timers_report_seconds_per_period_and_zero_once_idle():
    metrics = _log_metrics()
    memory = jm.MemoryWriter()
    state = metrics.init(1)
    with jm.Logger(metrics, [memory]) as logger:
        with logger.timer("rollout"):
            time.sleep(0.05)
        with logger.timer("rollout"):
            time.sleep(0.05)
        state = logger.flush(state, 0)
        state = logger.flush(state, 1)
    first, second = (x.scalars for x in memory.records)
    assert first["Timers/rollout"] >= 0.1
    assert second["Timers/rollout"] == 0.0


def test_timer_colliding_with_a_metric_tag_is_rejected_when_named():
    with jm.Logger(_log_metrics(), [jm.MemoryWriter()], timer_prefix="Train") as logger:
        with pytest.raises(ValueError, match="tag collision.*'Train/x'"):
            logger.timer("x")


def test_vmapped_seeds_flush_each_to_its_own_run():
    metrics = jm.Metrics(logged=["x"])
    memories = [jm.MemoryWriter() for _ in range(3)]
    seeds = jnp.arange(3, dtype=jnp.float32)
    state = jax.vmap(lambda _: metrics.init(1))(seeds)
    with jm.Logger(metrics, lambda run: [memories[run]], runs=3) as logger:
        for step in range(2):
            log = jax.vmap(lambda s, v: metrics.log(s, {"x": v}))
            state = logger.flush(log(state, seeds * 10 + step), jnp.array([5, 6, 7]) + step)
    for run, memory in enumerate(memories):
        assert [(r.step, r.scalars["Train/x"]) for r in memory.records] == [
            (5 + run, 10.0 * run),
            (6 + run, 10.0 * run + 1),
        ]


def test_flush_rejects_misuse_with_the_fix_in_the_message():
    metrics = _log_metrics()
    with jm.Logger(metrics, [jm.MemoryWriter()]) as logger:
        batched = jax.vmap(lambda _: metrics.init(1))(jnp.arange(3))
        with pytest.raises(ValueError, match="runs=3"):
            logger.flush(batched, 0)
        with pytest.raises(TypeError, match="logger.emit"):
            jax.jit(lambda s: logger.flush(s, 0))(metrics.init(1))
        with pytest.raises(TypeError, match="step must be an int"):
            logger.flush(metrics.init(1), 1.5)
    with pytest.raises(RuntimeError, match="closed"):
        logger.flush(metrics.init(1), 0)
    with pytest.raises(TypeError, match="function run -> writers"):
        jm.Logger(metrics, [jm.MemoryWriter()], runs=2)


def test_flush_moves_o_metrics_bytes_whatever_num_envs():
    metrics = jm.Metrics(terms={"r": jm.Term(lambda x: x, stats=("mean", jm.window(8)))})
    sizes = []
    for num_envs in (4, 4096):
        with jm.Logger(metrics, [jm.MemoryWriter()]) as logger:
            logger.flush(metrics.init(num_envs), 0)
            sizes.append(logger.report_nbytes)
    # mean, window mean/std/min/max + 8 window values as float32; nonfinite and the two
    # counters as uint32 hi/lo pairs.
    assert sizes == [(5 + 8) * 4 + 3 * 2 * 4] * 2


def test_loggers_of_a_spec_share_its_programs_and_they_go_with_the_spec():
    from jaxmetrics._host import _programs

    def report_once(metrics):
        with jm.Logger(metrics, [jm.MemoryWriter()]) as logger:
            state = metrics.log(metrics.init(1), {"x": jnp.float32(1.0)})
            state = logger.flush(state, 0)
            jax.jit(lambda s: logger.emit(s, 1, jnp.bool_(True)))(state)
            with jm.Logger(metrics, []) as other:
                assert other._programs is logger._programs  # nothing new to compile
        return len(_programs._CACHE)

    gc.collect()  # the specs of earlier tests that are already garbage
    before = len(_programs._CACHE)
    metrics = _log_metrics()
    assert report_once(metrics) == before + 1
    del metrics
    gc.collect()
    assert len(_programs._CACHE) == before


def test_packer_layout_comes_from_shapes_before_anything_is_traced():
    from jaxmetrics._host._transfer import Packer

    metrics = jm.Metrics(logged=["x"], counters=["u"])
    shapes = jax.eval_shape(lambda: metrics.compute(metrics.init(1)))
    packer = Packer(shapes, [i.tag for i in metrics.tags], jnp.float32)
    floats = np.arange(4, dtype=np.float32)
    counts = np.array([[0, 0, 1], [5, 2, 7]], np.uint32)  # hi and lo words
    assert packer.unpack(floats, counts) == {
        "Train/x": 0.0,
        "Train/x/std": 1.0,
        "Train/x/min": 2.0,
        "Train/x/max": 3.0,
        "Train/x/count": 5,
        "Train/x/nonfinite": 2,
        "Counters/u": 2**32 + 7,
    }
    state = metrics.increment(metrics.log(metrics.init(1), {"x": jnp.float32(3.0)}), "u")
    report = metrics.compute(state)
    got = packer.unpack(*(np.asarray(a) for a in jax.jit(packer.pack)(report)))
    want = metrics.to_host(report)
    assert got == want and list(got) == [i.tag for i in metrics.tags]
    with pytest.raises(ValueError, match="one Metrics spec"):
        packer.pack({k: v for k, v in report.items() if k != "Counters/u"})


def test_packer_lays_the_report_out_in_its_layout_and_unpacks_it_in_its_order():
    from jaxmetrics._host._transfer import Packer

    metrics = jm.Metrics(logged={"x": jm.Logged(stats=("mean", "max", jm.window(2)))})
    order = [i.tag for i in metrics.tags]
    state = metrics.log(metrics.init(1), {"x": jnp.array([1.0, 5.0, 2.0], jnp.float32)})
    report = metrics.compute(state)
    packer = Packer(jax.eval_shape(lambda: report), order, jnp.float32, layout=order[::-1])
    floats, counts = (np.asarray(a) for a in jax.jit(packer.pack)(report))
    got = packer.unpack(floats, counts)
    want = metrics.to_host(report)
    assert list(got) == order
    assert all(np.array_equal(got[t], want[t], equal_nan=True) for t in order)
    # The last float tag of the order lies first: the window's values, newest last.
    last = [t for t in order if not isinstance(report[t], jm.Count)][-1]
    assert last == "Train/x/window_values" and list(floats[:2]) == [5.0, 2.0]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_a_joined_report_parts_into_its_floats_and_counts_bit_for_bit(dtype):
    from jaxmetrics._host._transfer import Packer

    with jax.enable_x64(dtype == "float64"):
        metrics = jm.Metrics(logged=["x"], counters=["u"], dtype=dtype)
        shapes = jax.eval_shape(lambda: metrics.compute(metrics.init(1)))
        packer = Packer(shapes, [i.tag for i in metrics.tags], dtype)
        floats = jnp.asarray([-0.0, np.nan, -np.inf, 1e-45], dtype)  # signs, payloads
        counts = jnp.asarray([[0, 1, 2**32 - 1], [5, 2**31, 7]], jnp.uint32)
        runs = jax.vmap(packer.joined)((jnp.stack([floats, -floats]), jnp.stack([counts] * 2)))
        f, c = packer.parted(np.asarray(runs))
    assert f.dtype == np.dtype(dtype) and f.shape == (2, 4) and c.shape == (2, 2, 3)
    want = np.stack([np.asarray(floats), -np.asarray(floats)])
    assert f.tobytes() == want.tobytes()
    assert (c == np.asarray(counts)).all()


def _grouped(n: int) -> jm.Metrics:
    return jm.Metrics(
        terms={"r": jm.Term(lambda s: s["x"], stats=("mean", "std", "count"))},
        groups=jm.groups(lambda s: s["g"], tuple(f"g{i}" for i in range(n))),
    )


def test_the_report_program_does_not_grow_with_the_groups():
    """The flush packs the report's columns (a gather per run of tags), not a slice per
    tag: one per group and statistic made the first flush take minutes."""
    from jaxmetrics._host import _programs

    def ops(n):
        m = _grouped(n)
        compute = _programs.report_programs(m, 1, False).compute
        return len(re.findall(r"\bstablehlo\.\w+", jax.jit(compute).lower(m.init(4)).as_text()))

    assert ops(1000) == ops(10)


def test_a_flush_of_thousands_of_groups_records_each_group():
    n = 2000
    m = _grouped(n)
    k = np.arange(n) % (n // 2)  # even groups get the envs k and k + n/2, odd ones none
    x = np.arange(n, dtype=np.float32)
    update = jax.jit(m.update)  # op by op, a step's few hundred ops compile one by one
    state = update(m.init(n), {"x": x, "g": jnp.asarray(2 * k, jnp.int32)}, jnp.ones(n, bool))
    writer = jm.MemoryWriter()
    with jm.Logger(m, [writer]) as logger:
        logger.flush(state, step=1)
    (rec,) = writer.records
    for g in range(0, n, 2):
        tag = f"Episode_Metrics/r/g{g}"
        assert rec.scalars[tag] == pytest.approx(g // 2 + n / 4, rel=1e-6), tag
        assert rec.scalars[f"{tag}/std"] == pytest.approx(n / 4, rel=1e-6), tag
        assert rec.scalars[f"{tag}/count"] == 2, tag
    for g in range(1, n, 2):
        tag = f"Episode_Metrics/r/g{g}"
        assert tag not in rec.scalars and rec.scalars[f"{tag}/count"] == 0, tag


def test_a_flush_hands_back_the_carried_fields_themselves_and_fresh_period_statistics():
    stats = ("mean", "count", jm.ema(0.5), jm.window(3))
    metrics = jm.Metrics(
        terms={"r": jm.Term(lambda x: x, reduce="sum", stats=stats)},
        logged={"x": jm.Logged(stats=stats)},
    )
    state = metrics.init(4)
    state = metrics.update(state, jnp.arange(4.0), jnp.array([True, False, True, True]))
    state = metrics.log(state, {"x": jnp.array([1.0, 2.0], jnp.float32)})
    with jm.Logger(metrics, [jm.MemoryWriter()]) as logger:
        new = logger.flush(state, 0)
    fresh = metrics.init(4)
    for old, out, init in (
        (state.finished, new.finished, fresh.finished),
        (state.logged, new.logged, fresh.logged),
    ):
        for field in _stream.CARRIED:  # not copied: the very arrays
            pairs = zip(jax.tree.leaves(getattr(old, field)), jax.tree.leaves(getattr(out, field)))
            assert all(a is b for a, b in pairs), field
        for field in set(old._fields) - set(_stream.CARRIED):
            for a, b in zip(
                jax.tree.leaves(getattr(out, field)), jax.tree.leaves(getattr(init, field))
            ):
                assert np.array_equal(a, b, equal_nan=True), field
        assert int(old.count.lo.sum()) > 0
    assert new.running is state.running


def test_counters_past_2_to_the_32_reach_writers_exactly():
    metrics = jm.Metrics(counters=["samples"])
    memory = jm.MemoryWriter()
    big = 2**32 - 1
    state = metrics.init(1)
    with jm.Logger(metrics, [memory]) as logger:
        for step in range(3):
            state = logger.flush(metrics.increment(state, "samples", jnp.uint32(big)), step)
    assert [r.scalars["Counters/samples"] for r in memory.records] == [big, 2 * big, 3 * big]


def test_running_episodes_are_reported_on_request():
    metrics = jm.Metrics(terms={"r": lambda x: x})
    memory = jm.MemoryWriter()
    state = metrics.init(2)
    with jm.Logger(metrics, [memory], include_running=True) as logger:
        state = metrics.update(state, jnp.array([1.0, 3.0]), jnp.array([False, False]))
        state = metrics.update(state, jnp.array([3.0, 5.0]), jnp.array([False, False]))
        logger.flush(state, 0)
    scalars = memory.records[0].scalars
    assert scalars["Episode_Metrics/r/running"] == 3.0  # per-env step means 2 and 4
    assert "Episode_Metrics/r" not in scalars  # no episode finished: a gap


def test_flush_of_a_state_sharded_over_devices_equals_the_single_device_flush(env_sharded):
    metrics = jm.Metrics(terms={"r": jm.Term(lambda x: x, stats=("mean", "max", "count"))})
    x = jnp.arange(8.0, dtype=jnp.float32)
    done = jnp.arange(8) % 2 == 0
    scalars = []
    for place in (lambda a: a, lambda a: jax.device_put(a, env_sharded)):
        memory = jm.MemoryWriter()
        # CPU devices (the suite has 2), also where the default backend has one GPU.
        with jm.Logger(metrics, [memory]) as logger, jax.default_device(jax.devices("cpu")[0]):
            state = jax.jit(metrics.update)(metrics.init(8), place(x), place(done))
            logger.flush(state, 0)
        scalars.append(memory.records[0].scalars)
    assert scalars[0] == scalars[1]
    assert scalars[0]["Episode_Metrics/r/max"] == 6.0


_CHILD_NO_CLOSE = """
import sys, time
import jax.numpy as jnp
import jaxmetrics as jm
from jaxmetrics._core import _stream

class Slow(jm.JsonlWriter):
    def write(self, record):
        time.sleep(0.2)
        super().write(record)

metrics = jm.Metrics(logged=["x"])
logger = jm.Logger(metrics, [Slow(sys.argv[1])])
state = metrics.init(1)
for step in range(3):
    state = logger.flush(metrics.log(state, {"x": jnp.float32(step)}), step)
print("EXITING", flush=True)  # no close(): the interpreter exits with writes queued
"""


def test_an_unclosed_logger_is_drained_at_interpreter_exit(tmp_path):
    path = os.pathsep.join(p for p in (ROOT, os.environ.get("PYTHONPATH")) if p)
    env = dict(os.environ, PYTHONPATH=path, JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", _CHILD_NO_CLOSE, str(tmp_path / "m.jsonl")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 0 and out.stdout.strip() == "EXITING", out.stderr
    with open(tmp_path / "m.jsonl") as f:
        assert [json.loads(line)["scalars"]["Train/x"] for line in f] == [0.0, 1.0, 2.0]


def _compiled_emit(logger, state):
    return jax.jit(lambda s: logger.emit(s, 1, jnp.bool_(True))).lower(state).compile()


def test_a_report_to_a_logger_that_was_collected_is_dropped_loudly(caplog):
    """A compiled program holds its Logger's callback weakly (JAX may cache the traced
    program for the process's life): a report it makes after the Logger was collected is
    dropped with an error that says why, not written to a half-gone Logger."""
    metrics = _log_metrics()
    logger = jm.Logger(metrics, [jm.MemoryWriter()], report_channel="io_callback")
    state = metrics.log(metrics.init(1), {"x": jnp.float32(1.0)})
    compiled = _compiled_emit(logger, state)
    alive = weakref.ref(logger)
    logger.close()
    del logger
    gc.collect()
    assert alive() is None
    with caplog.at_level("ERROR", logger="jaxmetrics"):
        jax.block_until_ready(compiled(state))
        jax.effects_barrier()
    assert "reached a Logger that no longer exists" in caplog.text

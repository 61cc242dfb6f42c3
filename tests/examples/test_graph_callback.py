"""The graph-capturable host callback's prototype, on the CPU: its FFI handler (call frame,
attributes, metadata query) delivers each report of a jitted scan once, in order, with the
right bytes; the poll thread's ring reading, fed slots written as the device writes them.

References: the reports a hand-unrolled numpy loop computes; slot bytes packed by hand.
"""

import ctypes
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmetrics.bench import _graph_callback as gc

SHAPES = (jax.ShapeDtypeStruct((3,), jnp.float32), jax.ShapeDtypeStruct((2, 1), jnp.uint32))


def _collector():
    got, lock = [], threading.Lock()

    def receive(seq, arrays):
        with lock:
            got.append((seq, *(np.array(a) for a in arrays)))

    return got, receive


@pytest.mark.parametrize("slots", [1, 3])
def test_scan_delivers_each_report_once_in_order(slots):
    got, receive = _collector()
    cb = gc.GraphCallback(receive, SHAPES, gc.Mode.POLL, slots)
    steps, period = 23, 4

    def body(carry, _):
        x, t = carry
        x = x * jnp.float32(1.5) + jnp.float32(1.0)
        t = t + 1

        def fire():
            words = jnp.stack([t, t // period]).astype(jnp.uint32)[:, None]
            return cb(t // period, x, words)[1]

        x = jax.lax.cond(t % period == 0, fire, lambda: x)
        return (x, t), None

    run = jax.jit(lambda x: jax.lax.scan(body, (x, jnp.int32(0)), None, length=steps)[0])
    jax.block_until_ready(run(jnp.arange(3, dtype=jnp.float32)))
    cb.drain()
    cb.close()

    x, want = np.arange(3, dtype=np.float64), []
    for t in range(1, steps + 1):
        x = x * 1.5 + 1.0
        if t % period == 0:
            want.append((t // period, x.copy(), np.array([[t], [t // period]], np.uint32)))
    assert [g[0] for g in got] == [w[0] for w in want]
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g[1], w[1], rtol=1e-6)
        np.testing.assert_array_equal(g[2], w[2])
    assert gc._CALLS["cpu:metadata"] >= 1


def _slot(seq_begin, floats, words, seq_end):
    return (
        np.int32(seq_begin).tobytes()
        + np.asarray(floats, np.float32).tobytes()
        + np.asarray(words, np.uint32).tobytes()
        + np.int32(seq_end).tobytes()
    )


def test_poll_ring_reads_whole_slots_in_order_and_counts_lost():
    got, receive = _collector()
    cb = gc.GraphCallback(receive, SHAPES, gc.Mode.POLL, slots=4)
    ring = ctypes.create_string_buffer(cb.nbytes * 4)
    cb._pinned["cuda", 0] = ctypes.addressof(ring)

    def write(slot, raw):
        ctypes.memmove(ctypes.addressof(ring) + slot * cb.nbytes, raw, len(raw))

    def report(seq):
        return [seq, 0, 0], [[seq * 10], [seq]]

    # Reports 1-3 whole (written out of slot order), slot 3 torn: report 4 half written.
    for seq in (2, 1, 3):
        write(seq % 4, _slot(seq, *report(seq), seq))
    write(0, _slot(4, *report(4), 0))
    cb._take(0)
    cb.drain()
    assert [g[0] for g in got] == [1, 2, 3] and cb.lost == 0

    # Report 4 done; then 5-8 overwrite the whole ring before the next look: 4 is lost.
    for seq in (4, 5, 6, 7, 8):
        write(seq % 4, _slot(seq, *report(seq), seq))
    cb._take(0)
    cb.drain()
    cb.close()
    assert [g[0] for g in got] == [1, 2, 3, 5, 6, 7, 8] and cb.lost == 1
    for g in got:
        np.testing.assert_array_equal(g[1], np.array(report(g[0])[0], np.float32))
        np.testing.assert_array_equal(g[2], np.array(report(g[0])[1], np.uint32))


def test_bench_checks_the_reports_of_every_callback_variant():
    for variant in ("cond_io_callback", "cond_graph_poll_ring", "every_graph_poll"):
        row = gc.measure(variant, kernels=2, envs=16, steps=12, period=5, repeats=1, profile=False)
        assert row["delivered_right"], row["checks"]
        assert row["reports_per_call"] == (12 if variant.startswith("every") else 2)

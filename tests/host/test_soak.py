"""Soak: 10^5 flushes through one logger, and 200 loggers created and closed, with the
process's resident memory and thread count flat (slow: about two minutes)."""

import gc
import json
import os
import subprocess
import sys
import threading

import pytest

import jaxmetrics as jm

METRICS = jm.Metrics(logged=["x"], counters=["u"])


class _Counting:
    """A writer that keeps nothing but a count, so that any growth is the logger's."""

    def __init__(self):
        self.count = 0

    def open(self, tags):
        pass

    def write(self, record):
        self.count += 1

    def close(self):
        pass


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


_SOAK = """
import gc, os, threading, sys
sys.path.insert(0, os.path.dirname(sys.argv[1]))
from test_soak import METRICS, _Counting, _rss_mib
import jaxmetrics as jm

writer = _Counting()
state = METRICS.increment(METRICS.log(METRICS.init(0), {"x": 1.0}), "u")
threads = threading.active_count()
with jm.Logger(METRICS, [writer], max_pending=64) as logger:
    samples = []
    for step in range(100_000):
        state = logger.flush(state, step)
        if step % 10_000 == 9_999:
            logger.wait()
            gc.collect()
            samples.append(_rss_mib())
    assert threading.active_count() == threads + 1  # the one writer thread
assert writer.count == 100_000
assert threading.active_count() == threads
print(samples)
"""


@pytest.mark.slow
def test_1e5_flushes_keep_memory_and_threads_flat():
    # In a process of its own: a pytest worker's other residents (threads of earlier
    # tests' trackers, compilation caches) move its memory by several MiB on their own.
    out = subprocess.run(
        [sys.executable, "-c", _SOAK, __file__],
        capture_output=True,
        text=True,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert out.returncode == 0, out.stderr
    samples = json.loads(out.stdout.strip().splitlines()[-1])
    # After warm-up (the first sample) memory stays within a few MiB: no per-flush growth
    # (10^5 leaked records of ~1 KiB would be ~100 MiB).
    assert max(samples[1:]) - samples[1] < 8, samples


@pytest.mark.slow
def test_200_loggers_created_and_closed_keep_memory_and_threads_flat(tmp_path):
    state = METRICS.log(METRICS.init(0), {"x": 1.0})
    threads = threading.active_count()
    samples = []
    for i in range(200):
        writers = [_Counting(), jm.JsonlWriter(tmp_path / f"{i % 4}.jsonl")]
        with jm.Logger(METRICS, writers) as logger:
            logger.flush(state, i)
        assert threading.active_count() == threads
        if i % 40 == 39:
            gc.collect()
            samples.append(_rss_mib())
    assert max(samples[1:]) - samples[1] < 16, samples
    fds = len(os.listdir("/proc/self/fd"))
    with jm.Logger(METRICS, [jm.JsonlWriter(tmp_path / "last.jsonl")]):
        pass
    assert len(os.listdir("/proc/self/fd")) == fds  # every file is closed again

"""Two processes x 2 CPU devices under jax.distributed: one global env batch, the same
report as one process, only process 0 writes, and a flush moves O(metrics) bytes."""

import json
import os
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest
from multihost_spec import METRICS, NUM_ENVS, rollout_data
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

HERE = os.path.dirname(__file__)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def single_process_report():
    xs, dones, losses = rollout_data()

    def body(state, inp):
        x, d, loss = inp
        state = METRICS.update(state, x, d)
        return METRICS.log(state, {"loss": loss}), None

    state = jax.jit(lambda a, b, c: jax.lax.scan(body, METRICS.init(NUM_ENVS), (a, b, c))[0])(
        xs, dones, losses
    )
    return METRICS.to_host(METRICS.compute(state))


@pytest.mark.slow
def test_two_processes_report_what_one_process_reports_and_only_process_0_writes(tmp_path):
    port = free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=os.pathsep.join(sys.path))
    env.pop("XLA_FLAGS", None)
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                os.path.join(HERE, "multihost_worker.py"),
                str(i),
                str(port),
                str(tmp_path),
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(2)
    ]
    outs = [p.communicate(timeout=600)[0] for p in procs]
    for p, out in zip(procs, outs):
        assert p.returncode == 0, out
    results = [json.loads((tmp_path / f"report{i}.json").read_text()) for i in range(2)]
    want = single_process_report()
    for i, r in enumerate(results):
        assert r["shards"] == 4
        assert r["writes"] == (i == 0)
        assert r["report"].keys() == want.keys()
        for tag, v in want.items():
            np.testing.assert_allclose(
                np.asarray(r["report"][tag], np.float64),
                np.asarray(v, np.float64),
                rtol=2e-6,
                equal_nan=True,
                err_msg=f"process {i}: {tag}",
            )
    # A flush copies the packed report (a few floats per statistic), not the env batch.
    assert results[0]["flush_bytes"] < 2048
    assert not (tmp_path / "logs1").exists()
    lines = (tmp_path / "logs0" / "metrics.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    assert [r["step"] for r in records] == [1, 2]  # the flush, then the in-graph emit
    np.testing.assert_allclose(
        records[0]["scalars"]["Episode_Metrics/x"], want["Episode_Metrics/x"], rtol=2e-6
    )
    acc = EventAccumulator(str(tmp_path / "logs0" / "tb"))
    acc.Reload()
    steps = [e.step for e in acc.Scalars("Episode_Metrics/x/count")]
    assert steps == [1, 2]

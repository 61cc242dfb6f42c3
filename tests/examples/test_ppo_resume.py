"""The PPO demo's `--resume`: a run killed (SIGKILL) after a checkpoint, with records past
that checkpoint already written, and resumed writes exactly the records of an
uninterrupted run of the same command (JSONL and TensorBoard, two vmapped seeds)."""

import json
import os
import signal
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from tensorboard.backend.event_processing import event_accumulator

from jaxmetrics.examples import ppo

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SPI = 8 * 16  # env steps per iteration: --num-envs x --unroll-length
ITERATIONS = 12
SEEDS = ("0", "3")
# Brax's cheapest backend to compile (the runs compare records, whatever the physics).
FLAGS = [
    *("--backend", "spring", "--num-envs", "8", "--unroll-length", "16", "--episode-length", "10"),
    *("--steps", str(ITERATIONS * SPI), "--epochs", "2", "--minibatches", "2"),
    *("--seeds", *SEEDS, "--checkpoint-every", "3", "--jsonl", "--no-progress"),
]


def start(log_dir, *extra):
    # The suite's persistent compilation cache: the three runs share one program.
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": jax.config.jax_compilation_cache_dir}
    return subprocess.Popen(
        [sys.executable, "-m", "jaxmetrics.examples.ppo", *FLAGS, "--log-dir", log_dir, *extra],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def finish(proc):
    out, _ = proc.communicate(timeout=600)
    assert proc.returncode == 0, out


def jsonl_records(log_dir, seed):
    """The file's whole lines (a SIGKILL can leave a partial last one)."""
    path = os.path.join(log_dir, f"seed_{seed}", "metrics.jsonl")
    if not os.path.exists(path):
        return []
    with open(path) as f:
        return [json.loads(line) for line in f.read().split("\n")[:-1]]


def latest_checkpoint(log_dir):
    """The newest complete checkpoint's step (orbax renames a finished save to `<step>`)."""
    path = os.path.join(log_dir, "checkpoints")
    steps = [int(d) for d in os.listdir(path) if d.isdigit()] if os.path.isdir(path) else []
    return max(steps, default=None)


def kill_past_a_checkpoint(proc, log_dir):
    """SIGKILLs the run once a checkpoint exists and records after it are written.

    The run is stopped (SIGSTOP) before the files are checked, so what is checked is what
    the killed run leaves; if a newer checkpoint slipped in, it carries on and tries again.
    """
    while proc.poll() is None:
        if (ckpt := latest_checkpoint(log_dir)) is not None:
            if all(r and r[-1]["step"] > ckpt for r in (jsonl_records(log_dir, s) for s in SEEDS)):
                proc.send_signal(signal.SIGSTOP)
                ckpt = latest_checkpoint(log_dir)
                written = [jsonl_records(log_dir, s)[-1]["step"] for s in SEEDS]
                if min(written) > ckpt:
                    proc.kill()
                    proc.communicate(timeout=60)
                    return ckpt, written
                proc.send_signal(signal.SIGCONT)
        time.sleep(0.002)
    pytest.fail(f"the run ended (status {proc.returncode}) before it could be killed")


def scalar_events(run_dir):
    """tag -> [(step, value)] in file order, after TensorBoard's purge of restarted steps."""
    acc = event_accumulator.EventAccumulator(
        run_dir, size_guidance={event_accumulator.SCALARS: 0, event_accumulator.HISTOGRAMS: 0}
    )
    acc.Reload()
    scalars = {t: [(e.step, e.value) for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}
    hists = {
        t: [(e.step, e.histogram_value.bucket) for e in acc.Histograms(t)]
        for t in acc.Tags()["histograms"]
    }
    return scalars, hists


def rate(tag):
    return tag.endswith("/per_sec")  # wall-clock rates differ between any two runs


@pytest.mark.slow
def test_a_killed_and_resumed_run_writes_the_records_of_an_uninterrupted_run(tmp_path):
    whole, cut = str(tmp_path / "whole"), str(tmp_path / "cut")
    # The uninterrupted run first: it fills the compilation cache, which the run to kill
    # and its resume then read (run side by side, both compiled the same program).
    finish(start(whole))
    ckpt, written = kill_past_a_checkpoint(start(cut), cut)
    assert ckpt < ITERATIONS * SPI
    finish(start(cut, "--resume"))

    steps = [SPI * (i + 1) for i in range(ITERATIONS)]
    for seed in SEEDS:
        got, want = jsonl_records(cut, seed), jsonl_records(whole, seed)
        # Every step once, in order: the killed run's records past the checkpoint (up to
        # `written`) were dropped and written again by the resumed run.
        assert [r["step"] for r in got] == [r["step"] for r in want] == steps, written
        for g, w in zip(got, want):
            where = f"seed {seed} step {w['step']}"
            assert {t for t in g["scalars"] if not rate(t)} == {
                t for t in w["scalars"] if not rate(t)
            }, where
            # Same program, same inputs, one CPU: the values are bit-identical.
            for tag, value in w["scalars"].items():
                if not rate(tag):
                    assert g["scalars"][tag] == value, f"{where} {tag}"
            assert g["histograms"] == w["histograms"], where
            assert g["windows"] == w["windows"], where
        first = next(r for r in got if r["step"] == ckpt + SPI)
        assert "Counters/env_steps/per_sec" in first["scalars"]
        assert first["scalars"]["Counters/env_steps/per_sec"] > 0

        (got_s, got_h), (want_s, want_h) = (
            scalar_events(os.path.join(d, f"seed_{seed}")) for d in (cut, whole)
        )
        assert got_s.keys() == want_s.keys() and got_h.keys() == want_h.keys()
        for tag, events in want_s.items():
            assert [s for s, _ in got_s[tag]] == [s for s, _ in events], f"seed {seed} {tag}"
            if not rate(tag):
                np.testing.assert_array_equal(
                    [v for _, v in got_s[tag]], [v for _, v in events], err_msg=tag
                )
        for tag, events in want_h.items():
            assert got_h[tag] == events, f"seed {seed} {tag}"

    # A checkpoint is only resumed by the run that wrote it: other settings are named, and
    # refused before any writer could purge a record.
    other = ppo.PPOConfig(
        backend="spring",
        num_envs=8,
        unroll_length=16,
        episode_length=10,
        total_steps=2 * ITERATIONS * SPI,
        update_epochs=2,
        num_minibatches=2,
    )
    with pytest.raises(ValueError, match=r"settings \(total_steps: 1536 then, 3072 now\)"):
        ppo.train(other, cut, seeds=(0, 3), resume=True, progress=False)
    assert [r["step"] for r in jsonl_records(cut, SEEDS[0])] == steps

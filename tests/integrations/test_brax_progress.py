"""`jaxmetrics.brax.ProgressFn`: Brax's own PPO trainer reports through jaxmetrics writers.

The end-to-end test runs `brax.training.agents.ppo.train` for a tiny budget and compares
what TensorBoard's reader finds in the event files with the dicts Brax passed."""

import math
import os

import numpy as np
import pytest
from brax import envs
from brax.training.agents.ppo import train as brax_ppo
from tensorboard.backend.event_processing import event_accumulator

import jaxmetrics as jm
import jaxmetrics.brax as jmb


def read_scalars(run_dir) -> dict[str, dict[int, list[float]]]:
    """tag -> {step: [values in write order]}, read back by TensorBoard's own reader."""
    acc = event_accumulator.EventAccumulator(
        str(run_dir), size_guidance={event_accumulator.SCALARS: 0}
    )
    acc.Reload()
    out: dict[str, dict[int, list[float]]] = {}
    for tag in acc.Tags()["scalars"]:
        for e in acc.Scalars(tag):
            out.setdefault(tag, {}).setdefault(e.step, []).append(e.value)
    return out


# Every key Brax 0.14's PPO passes to progress_fn (plus env components and an unknown key)
# -> the tag the adapter documents.
LEARNER = {
    "policy_loss": "policy_loss",
    "v_loss": "value_loss",
    "entropy_loss": "entropy_loss",
    "total_loss": "total_loss",
    "kl_mean": "approx_kl",
    "learning_rate": "learning_rate",
    **{
        f"policy_dist_{s}_{p}": f"policy_dist_{s}_{p}"
        for s in ("min", "mean", "max")
        for p in ("loc", "std")
    },
}
EXPECTED = {
    "eval/episode_reward": "Eval_Metrics/episode_return",
    "eval/episode_reward_std": "Eval_Metrics/episode_return/std",
    "eval/avg_episode_length": "Eval_Metrics/episode_length",
    "eval/std_episode_length": "Eval_Metrics/episode_length/std",
    "eval/episode_reward_forward": "Eval_Metrics/reward_forward",
    "eval/episode_reward_forward_std": "Eval_Metrics/reward_forward/std",
    "eval/walltime": "Brax/eval/walltime",
    "eval/epoch_eval_time": "Brax/eval/epoch_eval_time",
    "eval/sps": "Brax/eval/sps",
    "training/sps": "Brax/training/sps",
    "training/walltime": "Brax/training/walltime",
    **{f"training/{k}": f"Train/{v}" for k, v in LEARNER.items()},
    "episode/sum_reward": "Episode_Metrics/episode_return/window_mean",
    "episode/length": "Episode_Metrics/episode_length/window_mean",
    "episode/reward_forward": "Episode_Metrics/reward_forward/window_mean",
    "episode/sps": "Brax/episode/sps",
    **{f"episode/{k}": f"Train/{v}/window_mean" for k, v in LEARNER.items()},
    "custom/thing": "Brax/custom/thing",
}


def test_brax_keys_map_to_library_tags(tmp_path):
    memory = jm.MemoryWriter()
    calls = [
        (0, {"eval/episode_reward": np.float32(4.5), "eval/episode_reward_std": 1.5}),
        (100, {k: float(i) for i, k in enumerate(EXPECTED)}),
        (100, {"episode/sum_reward": 7.0}),  # same step again: no rate
        (300, {"training/v_loss": math.nan, "episode/length": np.array(9.0)}),
    ]
    with jmb.ProgressFn([memory, jm.TensorBoardWriter(tmp_path)]) as progress_fn:
        for step, metrics in calls:
            progress_fn(step, metrics)
    records = memory.records
    assert [r.step for r in records] == [0, 100, 100, 300]
    assert records[0].scalars == {
        "Counters/env_steps": 0,
        "Eval_Metrics/episode_return": 4.5,
        "Eval_Metrics/episode_return/std": 1.5,
    }
    second = dict(records[1].scalars)
    rate = second.pop("Counters/env_steps/per_sec")
    assert rate == pytest.approx(100 / (records[1].wall_time - records[0].wall_time))
    assert second == {"Counters/env_steps": 100} | {
        tag: float(i) for i, tag in enumerate(EXPECTED.values())
    }
    assert "Counters/env_steps/per_sec" not in records[2].scalars
    # NaN is left out (a gap, not a 0); the rate spans 100 -> 300 from the first call at 100.
    assert records[3].scalars["Counters/env_steps/per_sec"] == pytest.approx(
        200 / (records[3].wall_time - records[1].wall_time)
    )
    assert "Train/value_loss" not in records[3].scalars
    tb = read_scalars(tmp_path)
    for record in records:
        for tag, value in record.scalars.items():
            assert np.float32(value) in np.float32(tb[tag][record.step]), tag
    assert 300 not in tb.get("Train/value_loss", {})


def test_bad_input_is_named():
    with pytest.raises(TypeError, match="wrap the writer in"):
        jmb.ProgressFn(jm.MemoryWriter())
    with pytest.raises(ValueError, match="prefixes must differ"):
        jmb.ProgressFn([], eval_prefix="Train")
    progress_fn = jmb.ProgressFn([jm.MemoryWriter()])
    with pytest.raises(TypeError, match="'eval/hist' is float64\\[3\\]"):
        progress_fn(0, {"eval/hist": np.zeros(3)})
    progress_fn.close()
    with pytest.raises(RuntimeError, match="after close"):
        progress_fn(0, {})


def test_a_run_that_fails_before_the_first_report_leaves_no_event_file(tmp_path):
    with pytest.raises(RuntimeError, match="Brax failed"):
        with jmb.ProgressFn([jm.TensorBoardWriter(tmp_path)]):
            raise RuntimeError("Brax failed before its first report")
    assert os.listdir(tmp_path) == []


@pytest.mark.slow
def test_brax_ppo_reports_through_the_writers(tmp_path, brax_ppo_on_this_jax):
    seen: list[tuple[int, dict[str, float]]] = []
    with jmb.ProgressFn([jm.TensorBoardWriter(tmp_path)]) as adapter:

        def progress_fn(step, metrics):
            seen.append((int(step), {k: float(v) for k, v in metrics.items()}))
            adapter(step, metrics)

        with jmb.default_promotion():  # the suite runs strict (conftest)
            brax_ppo.train(
                environment=envs.get_environment(
                    # Brax's cheapest backend to compile: the test reads what Brax
                    # reports, whatever the physics.
                    "inverted_pendulum",
                    backend="spring",
                ),
                num_timesteps=1024,
                episode_length=50,
                num_envs=16,
                batch_size=16,
                num_minibatches=2,
                unroll_length=8,
                num_updates_per_batch=1,
                num_evals=1,
                num_eval_envs=4,
                log_training_metrics=True,
                training_metrics_steps=512,
                max_devices_per_host=1,
                progress_fn=progress_fn,
                seed=0,
            )
    # Brax reported training-episode windows twice and, at the end, eval + learner values.
    assert [s for s, _ in seen] == [512, 1024, 1024]
    final = seen[-1][1]
    assert {"eval/episode_reward", "training/policy_loss", "training/v_loss"} <= set(final)
    tb = read_scalars(tmp_path)
    for step, metrics in seen:
        for key, value in metrics.items():
            tag = EXPECTED[key]
            # TensorBoard stores float32.
            assert np.float32(value) in np.float32(tb[tag][step]), (key, tag)
    assert tb["Counters/env_steps"][1024] == [1024.0, 1024.0]
    assert tb["Eval_Metrics/episode_return"][1024] == [pytest.approx(final["eval/episode_reward"])]
    assert tb["Train/value_loss"][1024] == [pytest.approx(final["training/v_loss"])]
    assert set(tb["Episode_Metrics/episode_return/window_mean"]) == {512, 1024}

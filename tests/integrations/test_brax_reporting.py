"""Brax's own `ppo.train` and `sac.train` with the reporting wrapper: every period's record
reaches TensorBoard while training runs, over all envs of both devices Brax pmaps over, equal
to a float64 unroll of the rewards and dones the training envs produced; the evaluator's
episodes are not in it; closing the logger after training writes everything once. Brax's env
resets between epochs lose nothing and keep Brax's step; a second training on one Logger is
refused."""

import functools
import re

import jax
import numpy as np
import pytest
from brax import envs
from brax.envs.base import Wrapper
from brax.envs.wrappers import training as brax_training
from brax.training.agents.ppo import train as brax_ppo
from brax.training.agents.sac import train as brax_sac
from jax.experimental import io_callback
from tensorboard.backend.event_processing import event_accumulator

import jaxmetrics as jm
import jaxmetrics.brax as jmb

DEVICES, NUM_ENVS, TIMESTEPS, REPORT_EVERY, WINDOW = 2, 16, 2048, 512, 100
# Brax's cheapest backend to compile (about half the time of mjx per training): what is
# checked is what the trainers report of the rewards and dones, whatever the physics.
BACKEND = "spring"


class Recorder(Wrapper):
    """Records each training step's reward and done (as the metrics see them) per device."""

    def __init__(self, env, seen):
        super().__init__(env)
        self.seen = seen

    def step(self, state, action):
        nstate = self.env.step(state, action)
        try:
            device = jax.lax.axis_index("i")
        except NameError:  # Brax's evaluator: not a training step
            return nstate

        def record(d, reward, done):
            self.seen.setdefault(int(d), []).append((np.asarray(reward), np.asarray(done)))

        io_callback(record, None, device, nstate.reward, nstate.done, ordered=True)
        return nstate


def _wrap(
    env,
    metrics,
    logger,
    seen,
    episode_length,
    action_repeat,
    randomization_fn,
    report_every: int | None = REPORT_EVERY,
):
    """`jmb.wrap`'s stack with the Recorder between the auto-reset and the metrics."""
    assert randomization_fn is None
    inner = jmb.MetricsWrapper(
        brax_training.VmapWrapper(env),
        metrics,
        episode_length,
        action_repeat,
        logger=logger,
        report_every=report_every,
    )
    return brax_training.AutoResetWrapper(Recorder(inner, seen))


def _reference(seen: dict[int, list], period_calls: int, epoch_calls: int = 0) -> list[dict]:
    """Per period: count, mean and max of episode returns and mean length, in float64,
    over the global env index (device d holds the d-th block of envs), and the mean of the
    last `WINDOW` returns. Every `epoch_calls` steps (0: never) the trainer resets the envs:
    the running episodes end unfinished."""
    rewards = np.concatenate([np.stack([r for r, _ in seen[d]]) for d in sorted(seen)], axis=1)
    dones = np.concatenate([np.stack([x for _, x in seen[d]]) for d in sorted(seen)], axis=1)
    ret = np.zeros(rewards.shape[1])
    length = np.zeros(rewards.shape[1])
    out, returns, lengths = [], [], []
    window: list[float] = []
    for t in range(rewards.shape[0]):
        if epoch_calls and t and t % epoch_calls == 0:
            ret[:] = length[:] = 0.0
        ret += rewards[t].astype(np.float64)
        length += 1
        for e in np.flatnonzero(dones[t]):
            returns.append(ret[e])
            lengths.append(length[e])
            window = (window + [ret[e]])[-WINDOW:]
            ret[e] = length[e] = 0.0
        if (t + 1) % period_calls == 0:
            out.append(
                {
                    "returns": np.asarray(returns),
                    "lengths": np.asarray(lengths),
                    "window_mean": np.mean(window),
                }
            )
            returns, lengths = [], []
    return out


def _read(logdir) -> dict[str, list[tuple[int, float]]]:
    acc = event_accumulator.EventAccumulator(
        str(logdir), size_guidance={event_accumulator.SCALARS: 0}
    )
    acc.Reload()
    return {t: [(e.step, e.value) for e in acc.Scalars(t)] for t in acc.Tags()["scalars"]}


def _ppo_settings(
    metrics: jm.Metrics, logger: jm.Logger, seen: dict, report_every: int | None = REPORT_EVERY
) -> dict:
    """Brax's ppo.train on inverted_pendulum, smoke-sized, over DEVICES devices, each
    training env reporting to `logger` every `report_every` env steps (its steps collected
    in `seen`)."""
    return dict(
        environment=envs.get_environment("inverted_pendulum", backend=BACKEND),
        num_timesteps=TIMESTEPS,
        episode_length=50,
        num_envs=NUM_ENVS,
        batch_size=16,
        num_minibatches=2,
        unroll_length=8,
        num_updates_per_batch=1,
        num_evals=2,
        num_eval_envs=4,
        max_devices_per_host=DEVICES,
        wrap_env_fn=functools.partial(
            _wrap, metrics=metrics, logger=logger, seen=seen, report_every=report_every
        ),
        seed=0,
    )


def _metrics() -> jm.Metrics:
    return jm.Metrics(
        terms={
            "return": jmb.episode_return(stats=("mean", "max", "count", jm.window(WINDOW))),
            "length": jmb.episode_length(stats=("mean", "count")),
        }
    )


def _check_records(logdir, seen: dict[int, list], epoch_calls: int = 0) -> None:
    """The records read back equal the float64 reference of the recorded training steps:
    one per period, in order, at env steps over both devices."""
    expected = _reference(seen, REPORT_EVERY // NUM_ENVS, epoch_calls)
    tb = _read(logdir)
    steps = [REPORT_EVERY * (k + 1) for k in range(TIMESTEPS // REPORT_EVERY)]
    assert [s for s, _ in tb["Counters/env_steps"]] == steps
    assert [v for _, v in tb["Counters/env_steps"]] == steps
    counts = [s for s, _ in tb["Episode_Metrics/return/count"]]
    assert counts == steps  # every period's record, in order, once
    for k, want in enumerate(expected):
        n = len(want["returns"])
        assert n > 0
        assert tb["Episode_Metrics/return/count"][k][1] == n
        assert tb["Episode_Metrics/length/count"][k][1] == n
        assert tb["Episode_Metrics/return"][k][1] == pytest.approx(want["returns"].mean(), rel=1e-5)
        assert tb["Episode_Metrics/return/max"][k][1] == pytest.approx(
            want["returns"].max(), rel=1e-5
        )
        assert tb["Episode_Metrics/length"][k][1] == pytest.approx(want["lengths"].mean(), rel=1e-6)
        assert tb["Episode_Metrics/return/window_mean"][k][1] == pytest.approx(
            want["window_mean"], rel=1e-5
        )


@pytest.fixture
def partitioner(request):
    """XLA's partitioner for the test: Shardy (JAX's default) or GSPMD, which Brax's
    ppo.train over 2 GPUs needs on JAX 0.11.2 (with Shardy the pmapped reset crashes XLA's
    compile there; docs/devices.md)."""
    before = jax.config.jax_use_shardy_partitioner
    jax.config.update("jax_use_shardy_partitioner", request.param == "shardy")
    yield request.param
    jax.config.update("jax_use_shardy_partitioner", before)


@pytest.mark.slow
@pytest.mark.parametrize(
    "partitioner, channel",
    # GSPMD with the ring: the writing device was once picked by axis_index, whose
    # partition-id GSPMD refused beside the ring's send (UNIMPLEMENTED).
    [("shardy", "auto"), ("gspmd", "ring")],
    indirect=["partitioner"],
)
def test_brax_ppo_train_reports_training_episodes_over_both_devices(
    tmp_path, brax_ppo_on_this_jax, partitioner, channel
):
    metrics = _metrics()
    seen: dict[int, list] = {}
    progress: list[tuple[int, set]] = []
    logger = jm.Logger(metrics, [jm.TensorBoardWriter(tmp_path)], report_channel=channel)
    with jmb.default_promotion():  # the suite runs strict (conftest)
        brax_ppo.train(
            **_ppo_settings(metrics, logger, seen),
            progress_fn=lambda step, m: progress.append((int(step), set(m))),
        )
    logger.close()
    # Brax trained on both devices and evaluated twice (its eval envs fold, never report).
    assert sorted(seen) == list(range(DEVICES))
    assert {len(v) for v in seen.values()} == {TIMESTEPS // NUM_ENVS}
    assert [s for s, keys in progress if "eval/episode_reward" in keys] == [0, TIMESTEPS]

    _check_records(tmp_path, seen)


@pytest.mark.slow
@pytest.mark.parametrize(
    "report_every, unreported, divisor",
    [
        # Brax's default period, 100 steps of the batch (1,600 env steps): one record.
        (
            None,
            r"wrote its last record at env step 1,600: the last 448 of the 2,048 env steps "
            r"Brax's trainer runs \(to its end\) are in no record, nor are the episodes",
            "1,024",
        ),
        (
            4096,
            r"wrote no record: none of the 2,048 env steps Brax's trainer runs \(to its "
            r"end\) is in one, nor are the episodes",
            "2,048",
        ),
    ],
)
def test_brax_ppo_train_s_unreported_tail_is_counted_at_close(
    tmp_path, brax_ppo_on_this_jax, report_every, unreported, divisor
):
    # close() said nothing of the env steps after the last record (ppo.train keeps its
    # final env state), and, with no record at all, not how many steps were lost.
    metrics = _metrics()
    seen: dict[int, list] = {}
    logger = jm.Logger(metrics, [jm.TensorBoardWriter(tmp_path)])
    with jmb.default_promotion():
        brax_ppo.train(**_ppo_settings(metrics, logger, seen, report_every))
    with pytest.warns(RuntimeWarning) as warned:
        logger.close()
    (message,) = [str(w.message) for w in warned]
    assert re.search(unreported, message), message
    assert "the steps after the last period end never reach the host" in message
    assert message.endswith(f"Pass a report_every that divides 2,048, e.g. {divisor}.")
    assert {len(v) for v in seen.values()} == {TIMESTEPS // NUM_ENVS}  # it ran to its end
    records = _read(tmp_path).get("Counters/env_steps", [])
    assert [s for s, _ in records] == ([1600] if report_every is None else [])


@pytest.mark.slow
def test_brax_env_resets_lose_nothing_and_a_second_training_is_refused(
    tmp_path, brax_ppo_on_this_jax
):
    # Brax resets the envs after each of its 2 epochs of 1,024 env steps
    # (num_resets_per_eval): records every 512 (the docs' advice, a divisor of the epoch)
    # keep Brax's step and every training episode, and windows run on through the reset;
    # closing warns of nothing (it used to, once per reset).
    metrics = _metrics()
    seen: dict[int, list] = {}
    progress: list[int] = []
    logger = jm.Logger(metrics, [jm.TensorBoardWriter(tmp_path)])
    settings = _ppo_settings(metrics, logger, seen) | dict(
        num_resets_per_eval=2, progress_fn=lambda step, m: progress.append(int(step))
    )
    with jmb.default_promotion():
        brax_ppo.train(**settings)
        assert progress == [0, TIMESTEPS]
        # A second training on the same Logger would go on from step 2,048 while Brax
        # counts from 0: refused when its env step is traced, naming the fix.
        with pytest.raises(ValueError, match=r"Create a new Logger for each training"):
            brax_ppo.train(
                **settings
                | {"wrap_env_fn": functools.partial(_wrap, metrics=metrics, logger=logger, seen={})}
            )
    logger.close()
    assert {len(v) for v in seen.values()} == {TIMESTEPS // NUM_ENVS}
    _check_records(tmp_path, seen, epoch_calls=TIMESTEPS // 2 // NUM_ENVS)


@pytest.mark.slow
def test_brax_sac_train_reports_its_prefill_and_training_steps(tmp_path, brax_ppo_on_this_jax):
    # SAC steps the env in two pmapped programs (the replay prefill, then the training
    # epochs) and resets it with an unnamed pmap; the records count both programs' steps.
    metrics = _metrics()
    seen: dict[int, list] = {}
    logger = jm.Logger(metrics, [jm.TensorBoardWriter(tmp_path)])
    with jmb.default_promotion():
        brax_sac.train(
            environment=envs.get_environment("inverted_pendulum", backend=BACKEND),
            num_timesteps=TIMESTEPS,
            episode_length=50,
            num_envs=NUM_ENVS,
            batch_size=16,
            min_replay_size=128,
            max_replay_size=TIMESTEPS,
            num_evals=2,
            num_eval_envs=4,
            max_devices_per_host=DEVICES,
            wrap_env_fn=functools.partial(_wrap, metrics=metrics, logger=logger, seen=seen),
            seed=0,
        )
    logger.close()
    assert sorted(seen) == list(range(DEVICES))
    assert {len(v) for v in seen.values()} == {TIMESTEPS // NUM_ENVS}
    _check_records(tmp_path, seen)

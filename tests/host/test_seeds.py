"""The cross-seed summary run (`Logger(runs=N, seeds_summary=...)`): read back from
TensorBoard's event files and compared with numpy float64 and scipy (`trim_mean` for the
IQM, `t.interval` for the 95% interval), with seeds missing or non-finite at a step."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from tensorboard.backend.event_processing import event_accumulator as ea

import jaxmetrics as jm
from jaxmetrics._host._seed_statistics import iqm, summarize

SEEDS = 5  # not a multiple of 4: the IQM cuts floor(n / 4) seeds at each end
STEPS = (10, 20, 30)
TAGS = ("Train/loss", "Train/loss/max", "Train/loss/count")


def _periods():
    """periods[p][seed]: the float32 values seed `seed` logs in period p. At step 20 seed
    1 logs a NaN (its mean and max are not finite); at step 30 seed 3 logs nothing."""
    rng = np.random.default_rng(7)
    periods = [[rng.normal(10.0 * s, 3.0, size=3).astype(np.float32) for s in range(SEEDS)]]
    periods.append([rng.normal(5.0 * s, 1.0, size=4).astype(np.float32) for s in range(SEEDS)])
    periods[1][1][2] = np.nan
    periods.append([rng.normal(-s, 2.0, size=2).astype(np.float32) for s in range(SEEDS)])
    periods[2][3] = np.zeros(0, np.float32)
    return periods


def _seed_reference(values):
    """A seed's record values in float64, non-finite ones left out (as a record does)."""
    v = np.asarray(values, np.float64)
    out = {"Train/loss/count": float(v.size)}
    if v.size:
        out.update({"Train/loss": v.mean(), "Train/loss/max": v.max()})
    return {t: x for t, x in out.items() if np.isfinite(x)}


def _summary_reference(per_seed):
    """tag -> stat -> value over the seeds that have a finite value, from scipy."""
    out = {}
    for tag in TAGS:
        x = np.array([r[tag] for r in per_seed if tag in r], np.float64)
        mean, sem = x.mean(), scipy.stats.sem(x)  # sem: ddof 1
        low, high = (
            scipy.stats.t.interval(0.95, x.size - 1, loc=mean, scale=sem)
            if sem > 0
            else (mean, mean)  # equal values: scipy has no interval of scale 0
        )
        out[tag] = {
            "": mean,
            "/seeds_std": x.std(ddof=1),
            "/seeds_min": x.min(),
            "/seeds_max": x.max(),
            "/seeds_iqm": scipy.stats.trim_mean(x, 0.25),
            "/seeds_ci_lower": low,
            "/seeds_ci_upper": high,
            "/seeds_count": float(x.size),
        }
    return out


def _select(mask, new, old):
    return jnp.where(mask.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("seeds")
    metrics = jm.Metrics(
        logged={
            "loss": jm.Logged(
                stats=("mean", "max", "count", jm.histogram(4, (0.0, 1.0))),
                nonfinite="propagate",
            )
        }
    )
    log = jax.jit(jax.vmap(lambda s, v: metrics.log(s, {"loss": v})))
    state = jax.vmap(lambda _: metrics.init(1))(jnp.arange(SEEDS))
    with jm.Logger(
        metrics,
        lambda run: [jm.TensorBoardWriter(root / f"seed_{run}")],
        runs=SEEDS,
        seeds_summary=[jm.TensorBoardWriter(root / "seeds_summary")],
    ) as logger:
        for step, period in zip(STEPS, _periods()):
            # Value i of every seed in one vmapped log, kept only for the seeds that have
            # an i-th value.
            for i in range(max(v.size for v in period)):
                has = np.array([v.size > i for v in period])
                vals = np.array([v[i] if v.size > i else 0.0 for v in period], np.float32)
                state = jax.tree.map(functools.partial(_select, has), log(state, vals), state)
            state = logger.flush(state, step)
        summary_tags = logger.summary_tags

    def read(run):
        acc = ea.EventAccumulator(str(root / run), size_guidance={ea.SCALARS: 0})
        acc.Reload()
        return {t: {e.step: e.value for e in acc.Scalars(t)} for t in acc.Tags()["scalars"]}

    return {
        "seeds": [read(f"seed_{s}") for s in range(SEEDS)],
        "summary": read("seeds_summary"),
        "summary_tags": summary_tags,
    }


def test_each_seed_has_its_own_run_beside_the_summary(written):
    for seed, scalars in enumerate(written["seeds"]):
        for step, period in zip(STEPS, _periods()):
            want = _seed_reference(period[seed])
            got = {t: scalars[t][step] for t in TAGS if step in scalars.get(t, {})}
            assert sorted(got) == sorted(want), (seed, step)
            for t, v in want.items():
                np.testing.assert_allclose(got[t], v, rtol=1e-6, err_msg=f"{seed} {t}@{step}")


def test_summary_matches_numpy_and_scipy_per_tag_and_step(written):
    summary = written["summary"]
    for step, period in zip(STEPS, _periods()):
        want = _summary_reference([_seed_reference(v) for v in period])
        for tag, stats in want.items():
            for suffix, v in stats.items():
                got = summary[tag + suffix][step]
                np.testing.assert_allclose(got, v, rtol=2e-6, atol=1e-6, err_msg=tag + suffix)
    # Seeds with a non-finite or missing value are left out of that tag's statistics.
    assert summary["Train/loss/seeds_count"] == {10: 5, 20: 4, 30: 4}
    assert summary["Train/loss/count/seeds_count"] == {10: 5, 20: 5, 30: 5}


def test_summary_covers_scalar_statistics_only(written):
    stats = {i.stat for i in written["summary_tags"]}
    assert stats == {
        "seeds_mean",
        "seeds_std",
        "seeds_min",
        "seeds_max",
        "seeds_iqm",
        "seeds_ci_lower",
        "seeds_ci_upper",
        "seeds_count",
    }
    assert {i.metric for i in written["summary_tags"]} == set(TAGS)  # no histogram
    assert set(written["summary"]) == {i.tag for i in written["summary_tags"]}


def test_summary_statistics_against_t_tables_and_trim_mean():
    # t(0.975, 1) = 12.7062047, t(0.975, 4) = 2.7764451 (standard tables).
    two = summarize([0.0, 1.0])
    assert two["seeds_ci_upper"] == pytest.approx(0.5 + 12.7062047 * np.sqrt(0.5) / np.sqrt(2))
    five = summarize([1.0, 2.0, 3.0, 4.0, 5.0])
    assert five["seeds_ci_lower"] == pytest.approx(3.0 - 2.7764451 * np.sqrt(2.5) / np.sqrt(5))
    one = summarize([4.0, np.inf])
    assert one == {
        "seeds_mean": 4.0,
        "seeds_min": 4.0,
        "seeds_max": 4.0,
        "seeds_iqm": 4.0,
        "seeds_count": 1,
    }
    assert summarize([np.nan]) == {}
    rng = np.random.default_rng(3)
    for n in range(1, 13):
        x = rng.normal(size=n)
        # Hand loop: cut floor(n / 4) at each end of the sorted values.
        k, s = n // 4, sorted(x.tolist())
        kept = s[k : n - k]
        assert iqm(x) == pytest.approx(sum(kept) / len(kept))
        assert iqm(x) == pytest.approx(scipy.stats.trim_mean(x, 0.25))


class Broken:
    def open(self, tags):
        pass

    def write(self, record):
        raise OSError("no space left")

    def close(self):
        pass


def test_summary_misuse_and_writer_errors():
    metrics = jm.Metrics(logged=["x", "x/seeds_std"])
    with pytest.raises(ValueError, match="tag collision: .*'Train/x/seeds_std'"):
        jm.Logger(metrics, lambda r: [], runs=2, seeds_summary=[jm.MemoryWriter()])
    plain = jm.Metrics(logged=["x"])
    with pytest.raises(ValueError, match="needs runs >= 2"):
        jm.Logger(plain, [], seeds_summary=[jm.MemoryWriter()])
    with pytest.raises(TypeError, match="wrap the writer in"):
        jm.Logger(plain, lambda r: [], runs=2, seeds_summary=jm.MemoryWriter())
    memory = jm.MemoryWriter()
    logger = jm.Logger(plain, lambda r: [], runs=2, seeds_summary=[Broken(), memory])
    state = jax.vmap(lambda v: plain.log(plain.init(1), {"x": v}))(jnp.array([1.0, 3.0]))
    logger.flush(state, 1)
    with pytest.raises(jm.WriterError, match="Broken.* of the seeds summary failed at step 1"):
        logger.close()
    (record,) = memory.records  # the other summary writer has it
    assert (record.scalars["Train/x"], record.scalars["Train/x/seeds_count"]) == (2.0, 2)

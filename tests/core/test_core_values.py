"""Inputs that once gave a wrong number without a word: wide host integers, values near
float32's limit, float16/bfloat16 inputs. Each is compared with numpy in float64."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxmetrics as jm
from jaxmetrics._core import _statistics


@pytest.mark.parametrize(
    "value",
    [
        np.int64(3_000_000_000),
        3_000_000_000,
        np.asarray([2**40, -(2**35), 7], np.int64),
        np.uint64(2**63 + 2**40),
        [2**31, 2**31 + 1],
    ],
)
def test_host_integers_past_int32_are_not_wrapped(value):
    # JAX without x64 holds int32: 3_000_000_000 once reported -1294967296.
    m = jm.Metrics(logged={"x": jm.Logged(stats=("mean", "min", "max", "sum"))})
    host = m.to_host(m.compute(m.log(m.init(0), {"x": value})))
    ref = np.asarray(value, np.float64).reshape(-1)
    for stat, want in (("", ref.mean()), ("/min", ref.min()), ("/max", ref.max())):
        assert host[f"Train/x{stat}"] == pytest.approx(want, rel=1e-7)
    assert host["Train/x/sum"] == pytest.approx(ref.sum(), rel=1e-6)


def test_term_returning_host_int64_is_not_wrapped():
    m = jm.Metrics(terms={"x": lambda s: np.full(2, 3_000_000_000, np.int64)})
    s = m.update(m.init(2), None, jnp.ones(2, bool))
    assert m.to_host(m.compute(s))["Episode_Metrics/x"] == pytest.approx(3e9, rel=1e-7)


@pytest.mark.parametrize("dtype", [jnp.bfloat16, jnp.float16])
def test_half_precision_inputs_reduce_in_float32(dtype):
    # bfloat16/float16 states once reported a mean of 1..1000 as 256 (or NaN); the state
    # is float32 and half-precision inputs are exact in it.
    m = jm.Metrics(terms={"x": jm.Term(lambda s: s, stats=("mean", "std", "sum", "count"))})
    values = np.arange(1, 1001, dtype=np.float64).reshape(250, 4)

    def body(s, v):
        return m.update(s, v.astype(dtype), jnp.ones(4, bool)), None

    s = jax.jit(lambda s, xs: jax.lax.scan(body, s, xs)[0])(m.init(4), jnp.asarray(values))
    host = m.to_host(m.compute(s))
    ref = values.astype(dtype).astype(np.float64).ravel()
    assert host["Episode_Metrics/x/count"] == 1000
    assert host["Episode_Metrics/x"] == pytest.approx(ref.mean(), rel=1e-6)
    assert host["Episode_Metrics/x/std"] == pytest.approx(ref.std(), rel=1e-5)
    assert host["Episode_Metrics/x/sum"] == pytest.approx(ref.sum(), rel=1e-6)


def test_each_row_counts_its_own_overflowed_statistics_whatever_the_rows_beside_it():
    # The overflow count is taken over whole columns of rows (a statistic that only some
    # rows have, percentiles that differ by row); the reference counts per row, from the
    # host report and the registry's overflow kinds.
    big = np.float32(3e38)
    full = ("mean", "std", "min", "max", "sum", "count", jm.ema(0.5), jm.window(2, (50,)))
    m = jm.Metrics(
        logged={
            "a": jm.Logged(stats=full),
            "b": jm.Logged(stats=("mean", "std", "sum", "count", jm.window(3, (10, 90)))),
            "c": jm.Logged(stats=full, nonfinite="propagate"),
            "d": jm.Logged(stats=("mean", "std", "sum", "count", jm.ema(0.5), jm.quantiles((50,)))),
            "e": jm.Logged(stats=("mean", "count", jm.window(2, (90,)))),
        }
    )
    data = {
        "a": [big, -big, big, -big],
        "b": [1.0, 2.0, 3.0],
        "c": [big, -big],
        "d": [-big, big, big, big],
        "e": [-big, big],
    }
    host = m.to_host(m.compute(m.log(m.init(0), data)))
    counted = {}
    for name in data:
        stats = {i.stat: i.tag for i in m.tags if i.metric == name}
        has = host[stats["count"]] > 0
        bad = 0
        for stat, tag in stats.items():
            kind = _statistics.get(stat).overflow
            v = np.asarray(host[tag], np.float64)
            bad += int(kind == "inf" and np.isinf(v)) + int(
                kind == "period" and has and not np.isfinite(v)
            )
        want = 0 if name == "c" else bad
        assert host[stats["nonfinite"]] == want, name
        counted[name] = bad
    assert counted["a"] > 0 and counted["c"] > 0 and counted["d"] > 0 and counted["e"] > 0
    assert counted["b"] == 0


def test_overflowed_statistics_are_counted_and_raised_at_flush():
    # Values near float32's limit: each is finite, their sum is not. The sum came out inf,
    # mean and std NaN, with /nonfinite 0, and the Logger dropped them without a word.
    m = jm.Metrics(
        logged={
            "big": jm.Logged(stats=("mean", "std", "sum"), nonfinite="raise"),
            "fine": jm.Logged(stats=("mean", "sum")),
        }
    )
    big = np.full(3, 3e38, np.float32)
    s = m.log(m.init(0), {"big": big, "fine": [1.0, 2.0]})
    host = m.to_host(m.compute(s))
    assert big.astype(np.float64).sum() > np.finfo(np.float32).max  # float32 cannot hold it
    assert host["Train/big/nonfinite"] > 0
    assert host["Train/fine/nonfinite"] == 0 and host["Train/fine/sum"] == 3.0
    memory = jm.MemoryWriter()
    with pytest.raises(jm.NonFiniteError, match=r"step 5, run 0: logged value 'big': .*overflow"):
        with jm.Logger(m, [memory]) as logger:
            logger.flush(s, 5)
    (record,) = memory.records
    assert "Train/big/sum" not in record.scalars  # never written as inf
    assert record.scalars["Train/fine"] == 1.5

"""10^8 float32 values of mean 1e4 and std 1: mean and std within 1e-6 relative of float64;
10^6 of them: the EMA within 1e-3 of their spread of a float64 EMA.

The values enter in chunks under `lax.scan`; the reference accumulates the same float32
values in float64 on the host. A naive float32 sum / sum-of-squares is shown to fail.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxmetrics as jm

TOTAL = 10**8
CHUNK = 10**6  # values per scan step
STEPS = 10  # scan steps per call: 10^7 values per call, 10 calls


def _chunks(rng):
    for _ in range(TOTAL // (CHUNK * STEPS)):
        # float32 values, as a float32 environment would produce them
        yield (1e4 + rng.standard_normal((STEPS, CHUNK), np.float32)).astype(np.float32)


def test_mean_and_std_of_1e8_values_within_1e6_of_float64():
    metrics = jm.Metrics(logged={"x": jm.Logged(stats=("mean", "std", "count", "sum"))})

    @jax.jit
    def feed(state, block):
        return jax.lax.scan(lambda s, v: (metrics.log(s, {"x": v}), None), state, block)[0]

    @jax.jit
    def naive(acc, block):
        def body(a, v):
            return (a[0] + jnp.sum(v), a[1] + jnp.sum(v * v)), None

        return jax.lax.scan(body, acc, block)[0]

    state = metrics.init(0)
    acc = (jnp.float32(0), jnp.float32(0))
    # float64 reference: x - 1e4 is exact in float64, so these sums are accurate to ~1e-16.
    s1 = s2 = 0.0
    for block in _chunks(np.random.default_rng(0)):
        state = feed(state, block)
        acc = naive(acc, block)
        d = block.astype(np.float64) - 1e4
        s1 += float(d.sum())
        s2 += float((d * d).sum())
    ref_mean = 1e4 + s1 / TOTAL
    ref_std = np.sqrt(s2 / TOTAL - (s1 / TOTAL) ** 2)

    host = metrics.to_host(metrics.compute(state))
    assert host["Train/x/count"] == TOTAL
    assert abs(host["Train/x"] - ref_mean) / ref_mean < 1e-6
    assert abs(host["Train/x/std"] - ref_std) / ref_std < 1e-6
    assert abs(host["Train/x/sum"] - ref_mean * TOTAL) / (ref_mean * TOTAL) < 1e-6

    # The naive float32 sum-of-squares variant (CLU's Std) fails the same bound.
    n = np.float32(TOTAL)
    naive_mean = acc[0] / n
    naive_var = jnp.maximum(acc[1] / n - naive_mean * naive_mean, 0)
    naive_std = float(jnp.sqrt(naive_var))
    assert abs(naive_std - ref_std) / ref_std > 1e-6


EMA_C = 0.01
EMA_VALUES = 10**6


def _far_from_zero() -> np.ndarray:
    return 1e4 + np.random.default_rng(1).standard_normal(EMA_VALUES, np.float32)


def _ema_reference(x: np.ndarray, c: float) -> float:
    # float64, sequential, RLlib's rule: seeded by the first value, no bias correction.
    e = float(x[0])
    for v in x[1:].tolist():
        e = c * v + (1 - c) * e
    return e


@pytest.mark.parametrize("per_step", [1, 1000])
def test_ema_of_1e6_values_far_from_zero_within_1e3_of_the_spread(per_step):
    # 10^6 float32 values of 1e4 + N(0, 1), `per_step` at a time: one by one, and 1000 per
    # step through the closed-form fold of a step's values.
    x = _far_from_zero()
    metrics = jm.Metrics(logged={"x": jm.Logged(stats=(jm.ema(EMA_C),))})

    @jax.jit
    def feed(state, block):
        return jax.lax.scan(lambda s, v: (metrics.log(s, {"x": v}), None), state, block)[0]

    state = feed(metrics.init(0), x.reshape(-1, per_step))
    got = metrics.to_host(metrics.compute(state))["Train/x/ema"]
    want = _ema_reference(x, EMA_C)
    spread = float(np.std(x.astype(np.float64)))
    assert abs(got - want) <= 1e-3 * spread, (got, want)


def test_ema_closed_form_without_offset_drifts_past_the_bound():
    # The same closed-form fold (1000 values per step, weights c(1-c)^(k-1-r), the old
    # EMA times (1-c)^k) held in plain float32 drifts well past 1e-3 of the spread: what
    # the offset in the state prevents.
    x = _far_from_zero()
    k = 1000
    c = jnp.float32(EMA_C)
    w = c * (1 - c) ** jnp.arange(k - 1, -1, -1, dtype=jnp.float32)
    w0 = w.at[0].set((1 - c) ** (k - 1))  # the first step's first value seeds the EMA

    @jax.jit
    def fold(block):
        def body(e, v):
            return (1 - c) ** k * e + jnp.sum(w * v), None

        return jax.lax.scan(body, jnp.sum(w0 * block[0]), block[1:])[0]

    want = _ema_reference(x, EMA_C)
    spread = float(np.std(x.astype(np.float64)))
    assert abs(float(fold(x.reshape(-1, k))) - want) > 2e-3 * spread


def test_one_pass_and_two_pass_batch_moments_agree():
    # Accelerators fold a batch in one reduction (Chan's pairwise moments in its
    # combiner), the CPU in two passes around a pivot; both on one input, on the CPU.
    from jaxmetrics._core import _stream

    rng = np.random.default_rng(3)
    v = (1e4 + rng.standard_normal((4, 4096))).astype(np.float32)
    v[1] = 5.0  # constant: no spread at all
    m = rng.random((4, 4096)) < 0.3
    m[3] = False  # nothing arrives
    nf = rng.integers(0, 2, (4, 4096)).astype(np.int32)
    # The EMA operand: weighted deviations, summed per row.
    dev = np.where(m, v - 1e4, 0).astype(np.float32)
    ema_in = jnp.asarray(0.01 * rng.random((4, 4096), np.float32) * dev)
    for shift in (np.zeros(4, np.float32), np.full(4, 1e4, np.float32)):
        args = (jnp.asarray(v), jnp.asarray(m), jnp.asarray(nf), jnp.asarray(shift))
        one = jax.jit(_stream.batch_one_pass, static_argnums=4)(*args, jnp.float32, ema_in)
        two = jax.jit(_stream.batch_two_pass, static_argnums=4)(*args, jnp.float32, ema_in)
        np.testing.assert_allclose(one[7], two[7], rtol=1e-5, atol=1e-6)
        for i in (0, 2, 3, 6):  # count, min, max, non-finite count: exact
            np.testing.assert_array_equal(one[i], two[i])
        np.testing.assert_allclose(one[1], two[1], rtol=1e-6)  # sum
        # Mean less the shift: unshifted (a period's first batch), the one-pass mean of
        # values near 1e4 is good to a few ulp of 1e4 only on the CPU's sequential chain.
        atol = 5e-3 if not shift.any() else 1e-4
        np.testing.assert_allclose(one[4], two[4], rtol=1e-6, atol=atol)
        # Squared deviations: the CPU runs the one-pass reduction as one sequential
        # Welford chain per row (why the CPU takes two passes), ~1e-4 off here.
        np.testing.assert_allclose(one[5], two[5], rtol=1e-3)
        assert float(one[5][1]) == 0.0 == float(two[5][1])


@pytest.mark.parametrize("width", [4096, 5000, 16384])
def test_one_pass_batch_reduces_long_rows_in_parts(width):
    # Past 4,096 entries the one reduction takes each row in parts of 256 entries (the
    # last padded with empty entries at 5,000), then the parts; against float64 numpy:
    # counts, min, max and sums of ints exact, the moments to float32 rounding.
    from jaxmetrics._core import _stream

    rng = np.random.default_rng(width)
    v = (1e4 + rng.standard_normal((4, width))).astype(np.float32)
    v[1] = 5.0  # constant: no spread at all
    m = rng.random((4, width)) < rng.choice([0.01, 0.3, 1.0], (4, 1))
    m[3] = False  # nothing arrives
    nf = rng.integers(0, 2, (4, width)).astype(np.int32)
    ema_in = rng.random((4, width)).astype(np.float32)
    counted = rng.integers(0, 3, (8, width)).astype(np.int32)
    shift = np.array([1e4, 0.0, 1e4 + 0.5, 0.0], np.float32)
    args = [jnp.asarray(a) for a in (v, m, nf, shift)]
    one = jax.jit(_stream.batch_one_pass, static_argnums=4)(
        *args, jnp.float32, jnp.asarray(ema_in), jnp.asarray(counted)
    )
    k, bsum, bmin, bmax, mean_dev, m2, bad, ema_sum, counted_sums = one
    np.testing.assert_array_equal(k, m.sum(axis=1))
    np.testing.assert_array_equal(bad, nf.sum(axis=1))
    np.testing.assert_array_equal(counted_sums, counted.sum(axis=1))
    np.testing.assert_allclose(ema_sum, ema_in.astype(np.float64).sum(axis=1), rtol=1e-5)
    for r in range(4):
        x = v[r, m[r]].astype(np.float64)
        assert (bmin[r], bmax[r]) == (x.min(initial=np.inf), x.max(initial=-np.inf))
        np.testing.assert_allclose(bsum[r], x.sum(), rtol=1e-6)
        d = x - float(shift[r])
        want = d.mean() if len(x) else 0.0
        # Deviations from a shift near the values are exact (Sterbenz); unshifted, the
        # mean of values near 1e4 is good to a few of their ulp (1e-3).
        atol = 5e-3 if shift[r] == 0 else 1e-6
        np.testing.assert_allclose(mean_dev[r], want, rtol=1e-6, atol=atol)
        np.testing.assert_allclose(m2[r], ((x - x.mean()) ** 2).sum() if len(x) else 0, rtol=1e-4)
    assert float(m2[1]) == 0.0


# ------------------------------------------------- the period mean at every arrival pattern

_MOMENTS = jm.Metrics(logged={"x": jm.Logged(stats=("mean", "std", "count"))})


@jax.jit
def _feed_moments(state, block, mask):
    """Logs block[t, :k_t] (the row's masked-in values) on step t."""

    def body(s, inp):
        v, m = inp
        # A row with fewer values: its masked-out slots are left out as non-finite.
        return _MOMENTS.log(s, {"x": jnp.where(m, v, jnp.nan)}), None

    return jax.lax.scan(body, state, (block, mask))[0]


def _moments_of(values: np.ndarray, per_step: int, total: int) -> dict:
    """Feeds `total` float32 values, `per_step` a step, through `Metrics.log`."""
    steps = -(-total // per_step)
    block = np.zeros(steps * per_step, np.float32)
    block[:total] = values
    mask = np.arange(steps * per_step) < total
    state = _MOMENTS.init(0)
    # Blocks of at most ~2^20 values per call keep the compile small and shared.
    rows = max(1, 2**20 // per_step)
    for i in range(0, steps, rows):
        state = _feed_moments(
            state,
            jnp.asarray(block.reshape(steps, per_step)[i : i + rows]),
            jnp.asarray(mask.reshape(steps, per_step)[i : i + rows]),
        )
    with np.errstate(all="ignore"):
        return _MOMENTS.to_host(_MOMENTS.compute(state))


def _check_moments(values: np.ndarray, host: dict) -> None:
    ref = values.astype(np.float64)
    assert host["Train/x/count"] == len(ref)
    mean, std = ref.mean(), ref.std()
    # Relative to the mean, or to the spread where the mean is near zero: a compensated
    # float32 sum is exact to a few ulp of its largest partial sums, not of the mean.
    tol = 1e-6 * max(abs(mean), std)
    assert abs(host["Train/x"] - mean) <= tol, (host["Train/x"], mean)
    assert abs(host["Train/x/std"] - std) <= 1e-4 * std, (host["Train/x/std"], std)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    per_step=st.sampled_from([1, 7, 64, 4096]),
    total=st.integers(1_000, 200_000),
    offset=st.sampled_from([0.0, 1.0, 1e4, -1e4, 1e6]),
    spread=st.sampled_from([1e-3, 1e-1, 1.0]),
    drift=st.sampled_from([0.0, 0.5, 3.0]),
    seed=st.integers(0, 2**16),
)
def test_period_mean_and_std_match_float64_at_every_arrival_pattern(
    per_step, total, offset, spread, drift, seed
):
    # Spreads from 1e-3 of the offset (of 1 where the offset is 0); the mean drifts by
    # `drift` spreads over the period.
    scale = spread * (abs(offset) if offset else 1.0)
    rng = np.random.default_rng(seed)
    x = offset + scale * (rng.standard_normal(total) + drift * np.linspace(0, 1, total))
    values = x.astype(np.float32)
    if values.astype(np.float64).std() == 0:
        return  # float32 rounded every value to one number: nothing to compare
    _check_moments(values, _moments_of(values, per_step, total))


def test_the_period_mean_keeps_moving_after_a_long_period():
    # One value per step: 10,000 values of 1e4, then 10^6 of 1e4 + 0.5. The running mean
    # used to stop at 10000.0 (true 10000.495) and the std read 0.4975 (true 0.0495).
    values = np.full(1_010_000, 1e4 + 0.5, np.float32)
    values[:10_000] = 1e4
    _check_moments(values, _moments_of(values, 1, len(values)))


def test_1e8_drifting_values_4096_a_step():
    # The far end of the regime: 10^8 values, offset 1e4, spread 1e-3 of it, drifting by
    # 3 spreads over the period.
    total = 10**8
    rng = np.random.default_rng(1)
    values = (
        1e4 + 10.0 * (rng.standard_normal(total, np.float32) + np.linspace(0, 3, total))
    ).astype(np.float32)
    _check_moments(values, _moments_of(values, 4096, total))


def _ema_of(x: np.ndarray, c: float, per_step: int) -> float:
    metrics = jm.Metrics(logged={"x": jm.Logged(stats=(jm.ema(c),))})

    @jax.jit
    def feed(state, block):
        return jax.lax.scan(lambda s, v: (metrics.log(s, {"x": v}), None), state, block)[0]

    state = feed(metrics.init(0), jnp.asarray(x, jnp.float32).reshape(-1, per_step))
    return metrics.to_host(metrics.compute(state))["Train/x/ema"]


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    c=st.sampled_from([1e-6, 3e-6, 1e-5, 3e-5, 1e-4]),
    per_step=st.sampled_from([1, 100]),
)
def test_ema_coefficient_is_not_rounded_through_float32_one_minus_c(c, per_step):
    # Values 0 (the seed), then 1: the EMA is 1 - (1-c)^n, so its effective coefficient
    # -log1p(-ema)/n shows how 1 - c was rounded (1e-6 acted as 1.013e-6, or 0.954e-6).
    n = 20_000
    x = np.r_[np.zeros(per_step), np.ones(n)].astype(np.float32)
    got = _ema_of(x, c, per_step)
    # Within what 20,000 float32 updates of a value in (0, 1) round to (about 1e-5).
    assert -np.log1p(-got) / n == pytest.approx(c, rel=1e-4)
    assert got == pytest.approx(_ema_reference(x, c), abs=2e-5)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    shape=st.sampled_from(["ramp", "step"]),
    size=st.sampled_from([1e3, 1e5, 1e6]),
    c=st.sampled_from([1e-4, 1e-3, 1e-2]),
    seed=st.integers(0, 2**16),
)
def test_ema_follows_values_that_move_far_from_its_seed(shape, size, c, seed):
    # Returns ramp during training: an offset fixed at seeding left the EMA with the
    # float32 resolution of the distance travelled (0 -> 1e5 ramp, c=1e-4: 16 off; 0
    # then 1e6 + N(0, 1): 168 off). Against RLlib's float64 rule, within 1e-2 of the
    # noise's sd plus float32's resolution of the values.
    rng = np.random.default_rng(seed)
    n, sd = 20_000, size / 1e3
    if shape == "ramp":
        x = np.linspace(0.0, size, n) + rng.normal(0.0, sd, n)
    else:
        x = np.r_[0.0, size + rng.normal(0.0, sd, n - 1)]
    x = x.astype(np.float32)
    got, want = _ema_of(x, c, 100), _ema_reference(x, c)
    assert abs(got - want) <= 1e-2 * sd + 2 * np.spacing(np.float32(size)), (got, want)


def test_ema_merge_refuses_coefficients_it_cannot_serve_exactly():
    # Two workers' EMAs were merged with the part older than their kept history (65,536
    # values each) estimated and still weighing (1-c)^65536: c = 1e-5 gave 50.16 for
    # 40.52. Such coefficients are refused where states are merged, naming the bound.
    small = jm.Metrics(terms={"r": jm.Term(lambda x: x, stats=(jm.ema(1e-5),))})
    merged = small.merge(small.init(2), small.init(2))  # the shards side by side
    with pytest.raises(ValueError, match=r"metric 'r': ema\(1e-05\) cannot be merged .*0.0003384"):
        small.compute(merged)  # where they meet
    mesh = jax.make_mesh((2,), ("env",), devices=jax.devices("cpu")[:2])
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("env"))
    with pytest.raises(ValueError, match=r"cannot be merged across devices"):
        small.init(4, sharding=sharding)
    small.init(4)  # one device: no merge, any coefficient
    ok = jm.Metrics(terms={"r": jm.Term(lambda x: x, stats=(jm.ema(3.4e-4),))})
    ok.compute(ok.merge(ok.init(2), ok.init(2)))

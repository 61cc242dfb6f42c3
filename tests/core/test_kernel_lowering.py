"""The fused kernels lowered for a CUDA GPU on this machine. Pallas' Triton lowering runs
when the update is lowered, so what Triton rejects and Pallas' interpret mode (the other
kernel tests) accepts fails here too, not only on a GPU: arrays whose sizes are not powers
of two, a `cond` on a constant predicate. Each case is one way the kernels read a batch."""

import jax
import jax.numpy as jnp
import pytest
from jax import export

import jaxmetrics as jm

TRITON = "__gpu$xla.gpu.triton"


def _spec(features: str, groups: int) -> jm.Metrics:
    """Four terms reading rows of a `[4, E]` input; "full": with EMAs, windows and two
    histograms, else period statistics only; each env in group `row 0 * groups`."""
    if features == "full":
        stats = {
            "a": ("mean", "std", jm.ema(0.05), jm.window(7, percentiles=(50,))),
            "b": ("max", jm.histogram(20, (0.0, 1.0)), jm.window(5)),
            "c": ("min", jm.histogram(5, (-1.0, 1.0)), jm.ema(0.5)),
            "d": ("sum", "count"),
        }
    else:
        stats = {"a": ("mean", "std"), "b": ("max",), "c": ("min",), "d": ("sum", "count")}
    reduce = {"a": "mean", "b": "max", "c": "min", "d": "sum"}
    terms = {
        k: jm.Term(lambda x, i: x[i], reduce=reduce[k], stats=v, params={"i": i})
        for i, (k, v) in enumerate(stats.items())
    }
    grouping = None
    if groups:
        names = tuple(f"g{k}" for k in range(groups))
        grouping = jm.groups(lambda x, n: (x[0] * n).astype(jnp.int32), names, n=groups)
    return jm.Metrics(terms=terms, groups=grouping)


@pytest.mark.parametrize(
    ("num_envs", "groups", "features"),
    [
        (256, 0, "full"),  # one program per row
        (3000, 0, "full"),  # chunks that count the row's mask, two blocks each
        (4097, 0, "full"),  # chunks that count the row's mask, the last one overlapping
        (12288, 0, "full"),  # the same, the mask read in two blocks of 8,192
        (16384, 0, "full"),  # chunks of 2,048 that count the row's mask
        (24576, 0, "full"),  # rows read from the lists, chunks of 2,048 listed
        (65536, 0, "full"),  # the same, chunks of 4,096 listed
        (300, 3, "full"),  # group rows from the lists, histograms counted in the kernel
        (4096, 64, "full"),
        (1024, 2, "simple"),  # group rows of period statistics, from the batch
        (4096, 8, "simple"),
        (24577, 0, "simple"),  # period statistics alone: chunks of 4,096, the last overlapping
        (65536, 0, "simple"),
    ],
)
def test_fused_kernels_lower_to_triton_for_cuda(monkeypatch, num_envs, groups, features):
    # As on a GPU: the segment rows' choice reads the default backend at trace time.
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    metrics = _spec(features, groups)
    args = (
        metrics.init(num_envs),
        jnp.zeros((4, num_envs), jnp.float32),
        jnp.zeros(num_envs, bool),
    )
    lowered = export.export(
        jax.jit(metrics.update),
        platforms=["cuda"],
        disabled_checks=[export.DisabledSafetyCheck.custom_call(TRITON)],
    )(*args)
    assert TRITON in lowered.mlir_module()

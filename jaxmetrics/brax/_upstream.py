"""Running Brax and MuJoCo from jaxmetrics: under JAX's default promotion, and without two
known notices where you ask for that.

Importing `jaxmetrics.brax` changes nothing in the process: no warnings filter, no redirected
output. `quiet_upstream()` hides the two notices inside its block only.
"""

import contextlib
import io
import sys
import warnings
from collections.abc import Iterator

import jax

_WARP_LINES = ("Failed to import warp:", "Failed to import mujoco_warp:")


@contextlib.contextmanager
def default_promotion() -> Iterator[None]:
    """Runs the block under JAX's default dtype and rank promotion.

    Brax, MJX and optax rely on implicit promotion (e.g. a float32 array times a Python
    float, or `[N]` against `[N, 1]`); under `jax_numpy_dtype_promotion="strict"` or
    `jax_numpy_rank_promotion="raise"` they fail. `MetricsWrapper` calls the inner env
    under this; wrap your own calls into Brax or MJX the same way when your config is
    strict. Terms still run under your config.

    Examples:
      >>> import jax, jax.numpy as jnp, jaxmetrics.brax as jmb
      >>> with jax.numpy_rank_promotion("raise"), jmb.default_promotion():
      ...     (jnp.ones(2) + jnp.ones((3, 1))).shape
      (3, 2)
    """
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        yield


@contextlib.contextmanager
def quiet_upstream() -> Iterator[None]:
    """Inside the block, two known upstream notices are hidden, nothing else.

    - MuJoCo prints "Failed to import warp: ..." and "Failed to import mujoco_warp: ..." to
      standard output when it is first imported without its optional warp backend
      (harmless: MJX runs on JAX). Those two lines are dropped; any other output goes
      through, after the block.
    - Brax's `brax.io.mjcf` warns on every env it builds that its own physics pipelines are
      "not actively being maintained" (MJX, which these envs run on, is). That one
      `UserWarning` is ignored; the warnings filters are restored after the block.

    Both are process-wide while the block runs (`sys.stdout` and `warnings.filters`), as
    `contextlib.redirect_stdout` and `warnings.catch_warnings` are: wrap the imports and
    the env builds, not a training loop that other threads print from.

    Examples:
      >>> import jaxmetrics.brax as jmb
      >>> with jmb.quiet_upstream():
      ...     from brax import envs
      ...     env = envs.get_environment("inverted_pendulum", backend="mjx")
    """
    captured = io.StringIO()
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(captured):
            warnings.filterwarnings(
                "ignore",
                message="Brax System, piplines and environments are not actively being maintained",
                category=UserWarning,
                module=r"brax\.io\.mjcf",
            )
            yield
    finally:
        kept = captured.getvalue().splitlines(keepends=True)
        sys.stdout.write("".join(line for line in kept if not line.startswith(_WARP_LINES)))

"""Running Brax and MuJoCo from jaxmetrics: under JAX's default promotion, without two
known notices.

Importing this module (`import jaxmetrics.brax` does, before anything imports Brax):

- imports MuJoCo's MJX with the two lines it prints when its optional warp backend is
  not installed ("Failed to import warp: ...", "Failed to import mujoco_warp: ...")
  left out of standard output; any other output of that import still goes through;
- adds one warnings filter, for the `UserWarning` that Brax's `brax.io.mjcf` raises on
  every env it builds ("Brax System, piplines and environments are not actively being
  maintained ..."; MJX, which these envs run on, is). Nothing else is filtered.
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
def _without_warp_lines() -> Iterator[None]:
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            yield
    finally:
        kept = captured.getvalue().splitlines(keepends=True)
        sys.stdout.write("".join(line for line in kept if not line.startswith(_WARP_LINES)))


with _without_warp_lines():
    import mujoco.mjx  # noqa: F401  (imported here, once, for its side effect only)

warnings.filterwarnings(
    "ignore",
    message="Brax System, piplines and environments are not actively being maintained",
    category=UserWarning,
    module=r"brax\.io\.mjcf",
)

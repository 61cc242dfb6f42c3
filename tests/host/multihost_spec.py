"""The spec and data shared by the multi-process test and its worker processes."""

import numpy as np

import jaxmetrics as jm

NUM_ENVS, STEPS = 16, 40
METRICS = jm.Metrics(
    terms={
        "x": jm.Term(
            lambda x: x[0],
            reduce="sum",
            stats=("mean", "std", "min", "max", "count", jm.ema(0.2), jm.window(8, (50,))),
        ),
        "y": jm.Term(lambda x: x[1], reduce="max", stats=("mean", jm.histogram(5, (0.0, 3.0)))),
    },
    logged=["loss"],
)


def rollout_data():
    rng = np.random.default_rng(7)
    xs = rng.normal(1.0, 1.0, (STEPS, 2, NUM_ENVS)).astype(np.float32)
    dones = rng.random((STEPS, NUM_ENVS)) < 0.3
    losses = rng.normal(size=STEPS).astype(np.float32)
    return xs, dones, losses

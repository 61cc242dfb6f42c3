"""MuJoCo Playground integration: `wrap` (Playground's `wrap_for_brax_training` with
metrics folded on every sub-step), the ready-made terms, and `ProgressFn` for the Brax PPO
trainer that Playground's `learning/train_jax_ppo.py` runs.

Playground trains its envs through Brax's `VmapWrapper` and `EpisodeWrapper`, its own
auto-reset and Brax's trainers, so this module reuses `jaxmetrics.brax`'s
`MetricsWrapper`, `Transition`, terms and `ProgressFn`; what differs is the env type
(`mujoco_playground.MjxEnv`), the auto-reset wrapper (Playground's), and the state that
terms read (`state.data` is the `mjx.Data`, so `joint_velocity` reads `data.qvel`).
Importing this module imports `mujoco_playground`; `import jaxmetrics` does not.
"""

from ..brax import default_promotion as default_promotion  # first: before Brax

# isort: split
from ..brax import MetricsWrapper as MetricsWrapper
from ..brax import ProgressFn as ProgressFn
from ..brax import Transition as Transition
from ..brax import control_effort as control_effort
from ..brax import episode_length as episode_length
from ..brax import episode_return as episode_return
from ..brax import metrics_state as metrics_state
from ..brax import replace_metrics_state as replace_metrics_state
from ..brax import state_metrics as state_metrics
from ..brax import success_rate as success_rate
from ..brax import termination_rate as termination_rate
from ..brax import truncation_rate as truncation_rate
from ._terms import joint_velocity as joint_velocity
from ._wrapper import wrap as wrap

__all__ = [
    "MetricsWrapper",
    "ProgressFn",
    "Transition",
    "control_effort",
    "default_promotion",
    "episode_length",
    "episode_return",
    "joint_velocity",
    "metrics_state",
    "replace_metrics_state",
    "state_metrics",
    "success_rate",
    "termination_rate",
    "truncation_rate",
    "wrap",
]

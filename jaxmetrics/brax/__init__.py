"""Brax integration: a `MetricsWrapper` (Brax's `EpisodeWrapper` plus metrics) and
ready-made terms over its `Transition`, and `ProgressFn`, a `progress_fn` for Brax's own PPO
trainer that writes through jaxmetrics writers.

Wrapper order: `AutoResetWrapper(MetricsWrapper(VmapWrapper(env), metrics, episode_length))`,
built by `wrap`. Importing this module imports Brax; `import jaxmetrics` does not. Neither
changes anything in the process; `quiet_upstream()` hides MuJoCo's "Failed to import warp"
lines and Brax's "not actively being maintained" warning inside its block.
"""

from ._upstream import default_promotion as default_promotion  # first: before Brax
from ._upstream import quiet_upstream as quiet_upstream

# isort: split
from .._core._success import success_rate as success_rate
from ._progress import ProgressFn as ProgressFn
from ._terms import control_effort as control_effort
from ._terms import episode_length as episode_length
from ._terms import episode_return as episode_return
from ._terms import joint_velocity as joint_velocity
from ._terms import state_metrics as state_metrics
from ._terms import termination_rate as termination_rate
from ._terms import truncation_rate as truncation_rate
from ._wrapper import MetricsWrapper as MetricsWrapper
from ._wrapper import Transition as Transition
from ._wrapper import metrics_state as metrics_state
from ._wrapper import replace_metrics_state as replace_metrics_state
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
    "quiet_upstream",
    "replace_metrics_state",
    "state_metrics",
    "success_rate",
    "termination_rate",
    "truncation_rate",
    "wrap",
]

"""Report statistics over a stream of values: one row per metric, stacked.

A stream receives batches `values[R, B]` with a boolean `mask[R, B]`; within a row, the
masked-in values arrive in ascending column order (for episodes: ascending env index).
Period statistics (count/mean/std/min/max/sum/histogram/quantile sketch/nonfinite) reset
with `reset_period`; EMA and windows persist.

Each `add` is one arrival step: `steps` counts them, and every value kept in a ring
buffer (windows, EMA history) carries the step it arrived on. That stamp is what lets
`merge` interleave the streams of disjoint workers (the env shards of one sharded state,
or separate states) in arrival order: by step, then worker order, then order within the
batch, which for env shards is ascending global env index.

All rows are stacked so that one fused XLA kernel serves every metric, whatever their
number: the per-step cost grows with rows x envs elementwise, not with kernel launches.

The package, one job a module: `_state` (the state, its plan, the rings), `_fold` (a
batch into the state), `_update` (a batch's statistics into the per-row fields), `_hists`
(a batch into the histograms), `_selected` (a batch's rows as source rows masked to a
group), `_segments` (group rows of period statistics by segment reductions), `_merge`
(states of disjoint workers into one) and `_compute` (the report statistics).
"""

from ._compute import compute as compute
from ._fold import add as add
from ._fold import add_with_counts as add_with_counts
from ._fold import arrivals_after as arrivals_after
from ._fold import batch_one_pass as batch_one_pass
from ._fold import batch_two_pass as batch_two_pass
from ._fold import counts_width as counts_width
from ._hists import slot_counts_compare as slot_counts_compare
from ._hists import slot_counts_scatter as slot_counts_scatter
from ._merge import check_mergeable as check_mergeable
from ._merge import combine as combine
from ._merge import merge as merge
from ._merge import pad_ema_history as pad_ema_history
from ._merge import spread as spread
from ._merge import with_ema_history as with_ema_history
from ._segments import SegmentPlan as SegmentPlan
from ._segments import segment_batch as segment_batch
from ._selected import Selected as Selected
from ._state import CARRIED as CARRIED
from ._state import MAX_EMA_HISTORY as MAX_EMA_HISTORY
from ._state import Ring as Ring
from ._state import StreamPlan as StreamPlan
from ._state import StreamState as StreamState
from ._state import carried as carried
from ._state import init as init
from ._state import reset_period as reset_period
from ._state import uncarried as uncarried

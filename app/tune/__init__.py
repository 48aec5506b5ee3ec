"""Parameter sweeps and searches: a grid or an Optuna TPE search over any parameters of the
stage table, every trial evaluated on every frame of a dataset (frames on Dask, see
:mod:`app.distributed`), every trial kept in a store that survives a kill.

A *space* file (TOML) names the parameters that vary, one table per stage::

    [reliability]
    eps1 = { low = 2.0, high = 20.0 }               # a range (float: continuous)
    threshold = { low = 0.5, high = 0.95, step = 0.05 }
    [stereo]
    window = [5, 7, 9, 11]                          # choices
    [spline]
    n_ctrl = { low = 8, high = 30 }                 # an integer parameter: integers
    xy_knots = ["uniform", "adaptive"]

Every bound and choice is checked against the parameter's declaration (``core.params``). A grid
needs choices or a ``step`` on every float range (integer ranges step by 1 unless told).

Objectives (:data:`OBJECTIVES`) are computed from the per-frame rows of
:func:`app.evaluation.evaluate_frame`; constraints such as ``failure_rate<=0.02`` select the
feasible trials. The store is a folder: ``study.sqlite3`` (Optuna's RDB storage: each trial's
parameters, per-frame rows, objectives and constraint values), ``tune.json`` (what the run
is; a resume must match it), ``trials.csv`` and ``frames.csv`` (written at the end). Running the
same command again resumes: finished trials are kept, a trial cut short by a kill is run again.

Trials run one after another, each on all frames at once, and the TPE sampler is seeded from
``--seed`` and the number of finished trials: the sequence of trials depends only on the store,
never on how many workers ran them.
"""

from threadrecon.app.tune.config import (
    TrialResult,
    TuneConfig,
    TuneResult,
    check_config,
    split_frames,
)
from threadrecon.app.tune.report import compare_on, pick_best, save_best
from threadrecon.app.tune.run import (
    INTERRUPTED,
    STUDY_NAME,
    Stopped,
    open_study,
    target_trials,
    tune,
)
from threadrecon.app.tune.space import (
    DEFAULT_CONSTRAINTS,
    GRID_DIGITS,
    OBJECTIVES,
    RANGE_KEYS,
    Constraint,
    Dimension,
    Objective,
    Space,
    load_space,
    params_of,
    parse_space,
)

__all__ = [
    "OBJECTIVES",
    "Constraint",
    "DEFAULT_CONSTRAINTS",
    "Dimension",
    "GRID_DIGITS",
    "INTERRUPTED",
    "Objective",
    "RANGE_KEYS",
    "STUDY_NAME",
    "Space",
    "Stopped",
    "TrialResult",
    "TuneConfig",
    "TuneResult",
    "check_config",
    "compare_on",
    "load_space",
    "open_study",
    "params_of",
    "parse_space",
    "pick_best",
    "save_best",
    "split_frames",
    "target_trials",
    "tune",
]

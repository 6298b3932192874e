"""``metrics.csv``'s column names, defined once, below everything that reads or writes them.

Training writes the file (:mod:`unipolicy_rl.training.metrics_file`); the report, the
training-curve plot and the benchmarks read it. A column renamed on one side only would silently
drop a curve, so every side names its columns from here. Plain strings, no imports: the
evaluation and report packages read these without importing the training stack.
"""

from __future__ import annotations

FILE_NAME = "metrics.csv"  # in the run folder, next to checkpoint.pt

# -- every row --------------------------------------------------------------------------
EPOCH = "epoch"  # real epochs finished (imagined batches repeat their real epoch's number)
IMAGINED = "imagined"  # 1.0 on a batch of imagined (world-model) episodes, 0.0 on a real one
REAL_STEPS = "real_env_steps"  # cumulative real simulator steps used for training
ELAPSED = "time/elapsed"  # wall seconds since the run started, over resumes
COLLECT_TIME = "time/collect"  # seconds this batch took to collect
UPDATE_TIME = "time/update"  # seconds this batch's policy update (and bookkeeping) took
EPOCH_TIMES = (COLLECT_TIME, UPDATE_TIME)  # per-batch seconds; what older runs logged instead of ELAPSED
# CPU seconds (every core, worker processes included; training/cpu_time.py) the real epoch's
# collection and updates took, over the same span as its COLLECT_TIME + UPDATE_TIME; real rows only
CPU_TIME = "time/cpu"

# -- real episodes (blank on imagined rows) ------------------------------------------------
REWARD = "train/episode_reward"  # real episodes' mean return
REWARD_PER_STEP = "train/reward_per_step"  # mean real reward per step
DISPLACEMENT = "train/forward_displacement"  # real episodes' mean forward displacement (m)
SPEED = "train/forward_speed"  # real episodes' mean forward speed (m/s)
PHYSICS_FAULTS = "train/physics_faults"  # real steps the simulator faulted on
REFRESH_KL = "train/refresh_kl"  # policy KL caused by refreshing the observation normaliser

# -- the TRPO update (the updater logs more ``train/`` figures; these are the ones read back) ----
KL = "train/kl"  # mean KL(old || new) after the policy step (0 when none was accepted)
STEP_ACCEPTED = "train/step_accepted"  # 1.0 when the line search accepted a step
LINE_SEARCH_TRIES = "train/line_search_tries"  # candidate steps the line search evaluated

# -- periodic real-env evaluation on the design grid (blank on rows without one) ---------------
EVAL_PREFIX = "eval/"  # the periodic evaluation's columns
GRID_MEAN = EVAL_PREFIX + "grid_mean_displacement"  # mean forward displacement over the grid (m)
GRID_MIN = EVAL_PREFIX + "grid_min_displacement"  # the worst design's forward displacement (m)
GRID_WALKING = EVAL_PREFIX + "walking_designs"  # designs that walk
GRID_REWARD = EVAL_PREFIX + "grid_mean_reward"  # mean episode reward over the grid
# robot=grammar: the columns above are over every (morphology, design) cell; these per morphology.
WALKING_MORPHOLOGIES = EVAL_PREFIX + "walking_morphologies"  # morphologies whose own grid mean walks
WORST_MORPHOLOGY_MEAN = EVAL_PREFIX + "worst_morphology_mean_displacement"  # the lowest morphology grid mean (m)
# env=gym: the deterministic policy's returns over env.evaluation_episodes real episodes.
EVAL_RETURN = EVAL_PREFIX + "mean_return"  # their mean return
EVAL_MIN_RETURN = EVAL_PREFIX + "min_return"  # the lowest of them
# The evaluations' own cost so far, cumulative over the run (never counted in real_env_steps).
EVAL_EPISODES = EVAL_PREFIX + "episodes"  # evaluation episodes run (one per grid cell per evaluation)
EVAL_ENV_STEPS = EVAL_PREFIX + "env_steps"  # their env steps: episodes x episode length (a faulted one counts whole)
EVAL_SECONDS = EVAL_PREFIX + "seconds"  # this evaluation's wall seconds (in time/elapsed, not in the epoch's times)

# -- model-based sources -----------------------------------------------------------------
IMAGINED_PREFIX = "imagined/"  # imagined batches' figures: never real returns
IMAGINED_REWARD_PER_STEP = IMAGINED_PREFIX + "reward_per_step"  # mean imagined reward per step
IMAGINED_MAX_KL = IMAGINED_PREFIX + "max_kl"  # the imagined updates' KL bound (imagination.adaptive_kl)
MODEL_PREFIX = "model/"  # the world model's fit and surrogate accuracy
MODEL_VALIDATION_MSE = MODEL_PREFIX + "validation_mse"  # the elites' standardised held-out error
FRESH_ERROR = MODEL_PREFIX + "fresh_error"  # the model's error on the epoch's new real states, before its fit

# -- algo.policy_average (while on) -----------------------------------------------------
POLICY_AVERAGE_DISTANCE = "policy_average/distance"  # ||average - weights|| / ||weights||: how far the policy lags

"""The seed ranges of Meta-World episodes, each defined once here.

A Meta-World seed draws an episode's object and goal positions. The ranges never overlap, so no seed a policy is
evaluated on was collected, trained or distilled on:

* ``COLLECT_SEED_START`` (0, 1, ...): expert demonstrations (``hf-specvla collect``; a second collection takes
  ``--seed-start 5000``);
* ``EVAL_SEED_START`` (100000): evaluation (``eval``) and the paired comparison (``compare``);
* ``FIDELITY_SEED_START`` (200000): the comparison's second seed range, for a setting chosen on the first;
* ``BENCH_SEED_START`` (300000): the recorded rollouts ``bench-episodes`` replays;
* ``DRAFT_SEED_START`` (400000): the on-policy rollouts a draft head is distilled on (``train-draft``).
"""

COLLECT_SEED_START = 0
EVAL_SEED_START = 100_000
FIDELITY_SEED_START = 200_000
BENCH_SEED_START = 300_000
DRAFT_SEED_START = 400_000

#: every range's start, in order (each range holds the seeds up to the next start)
SEED_RANGES = {
    "collect": COLLECT_SEED_START,
    "eval": EVAL_SEED_START,
    "fidelity": FIDELITY_SEED_START,
    "bench": BENCH_SEED_START,
    "draft": DRAFT_SEED_START,
}

"""The seed ranges, apart so no episode serves two purposes: the test seeds every results table
is measured on (``TEST_SEED`` on, never used in training), the validation seeds checkpoints are
chosen on (``VALIDATION_SEED`` on), and the reward sanity sweep's own (``SANITY_SEED`` on).
Training episodes use ``seed * EPISODE_SEED_STRIDE + episode`` (``learning.trainer``)."""

TEST_SEED = 10_000
VALIDATION_SEED = 900_000
SANITY_SEED = 20_000

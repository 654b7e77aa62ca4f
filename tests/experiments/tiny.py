"""Overrides that shrink any experiment recipe to a few seconds: tiny networks, two fit steps."""

TINY = [
    "models.window=3",
    "models.world_model.hidden_size=4",
    "models.world_model.dense_size=4",
    "models.uncertainty.hidden_size=4",
    "training.slice_len=6",
    "training.num_slices=2",
    "training.world_model.steps=2",
    "training.world_model.eval_every=1",
    "training.uncertainty.steps=2",
    "training.uncertainty.eval_every=1",
    "logger.backend=none",
]

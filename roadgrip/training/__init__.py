"""Training: a trainer that knows nothing of the model it trains, cross-validation, and checkpoints that carry their config."""

"""Estimators of mu behind one interface (`Estimator`): the learned models, and later the physics filters."""

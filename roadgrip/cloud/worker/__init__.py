"""Per-vehicle estimation: the pipeline (reorder, estimator, storage writes), estimator checkpoints, and who runs
it (processes of one machine, or cluster workers that own partitions)."""

"""What is measured on one rollout or one set of rates, above the statistics and below the data: the world model's
metrics (r, MMRV, per-rollout outcomes), object permanence, locating and tracking objects, and action following."""

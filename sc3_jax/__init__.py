"""sc3_jax: a multi-view, action-conditioned video world model used as a faithful robot-policy evaluator."""

__version__ = "0.1.0"

"""Tiny CPU config: trains on the synthetic environment in minutes (tests, `sc3 demo`)."""
from sc3_jax.config import Config


def get_config(arg: str | None = None) -> Config:
    return Config(name="tiny")

"""The ground floor: what every other folder may use and which imports no other sc3_jax module -- the user-facing
error (``errors``), atomic writes, locks, safe names, the checks at the door (``validate``), ``module:attr`` specs,
the config dataclasses (``config``, ``tokenizer_config``), video writing and the compiled-cost reader."""

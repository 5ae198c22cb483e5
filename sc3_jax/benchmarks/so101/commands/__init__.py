"""The SO-101 benchmark's own ``sc3`` command (``so101.py``: ``sc3 so101``), with the contract of ``sc3_jax/commands/``;
``sc3_jax/cli.py`` finds it on disk, as the bussing benchmark's (``benchmarks/bussing/commands/``)."""
